"""libgpiod v2 line requests: the encoder lines' edge-event request and the motors' direction outputs.

The only module that imports the `gpiod` package (2.x, the `pi5` extra), and only inside the functions that open a
real request, so everything else runs and is tested without it. The rest of the back-end sees two small interfaces,
`EventLines` (a file descriptor of raw kernel events) and `OutputLines` (levels written at once), which the stand-ins
in drivers.virtual implement too.

The GPIO chip is found by its label, not its number: the RP1's is `pinctrl-rp1`, /dev/gpiochip4 on early Pi 5
kernels and /dev/gpiochip0 since 6.6.
"""

from __future__ import annotations

import errno
import glob
import importlib.util
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from datetime import timedelta
from typing import TYPE_CHECKING, Literal, Protocol

if TYPE_CHECKING:
    import gpiod

RP1_GPIO_LABEL = "pinctrl-rp1"
DEFAULT_EVENT_BUFFER = 1024
"""Events the kernel holds per request between two reads (its default is 16 per line; it caps the size at 1024)."""

Pull = Literal["up", "down", "off"]


class GpioUnavailableError(ConnectionError):
    """The GPIO chip, its lines or the PWM chip cannot be used; the message says why and what to do."""


@dataclass(frozen=True, slots=True)
class EventLineSettings:
    """How the encoder lines are requested: chip (None: find the RP1's), bias, debounce, kernel buffer."""

    chip: str | None = None
    pull: Pull = "up"
    debounce_us: int = 0
    """Kernel debounce per line (0: off). The RP1 has none in hardware: the kernel's software debounce costs a
    timer per edge, so keep it off at encoder rates."""
    event_buffer_size: int = DEFAULT_EVENT_BUFFER
    consumer: str = "robotd-encoders"


class EventLines(Protocol):
    """A line request with edge detection: raw `gpio_v2_line_event` records are read from `fd`."""

    @property
    def fd(self) -> int:
        """File descriptor the events are read from."""
        ...

    def levels(self) -> int:
        """The requested lines' present levels as a word (bit n = line n)."""
        ...

    def release(self) -> None:
        """Give the lines back (closes `fd`)."""
        ...


class OutputLines(Protocol):
    """A line request of outputs: several levels written in one call."""

    def set_values(self, values: Mapping[int, int]) -> None:
        """Drive each line (offset) of `values` to its level (0 or 1), all in one kernel call."""
        ...

    def release(self) -> None:
        """Give the lines back."""
        ...


EventLinesOpener = Callable[[Sequence[int], EventLineSettings], EventLines]
OutputLinesOpener = Callable[[Sequence[int], str | None], OutputLines]
LineHolders = dict[int, str | None]
LineHoldersReader = Callable[[Sequence[int], str | None], tuple[str, LineHolders]]
"""(the chip's path, each line's consumer: the name its holder gave, '' for a nameless one, None when it is free)."""


GPIOD_MINIMUM = (2, 2)
"""The oldest `gpiod` Python package with the libgpiod v2 API robotd uses (Debian Trixie's python3-libgpiod)."""


def gpiod_version() -> str | None:
    """The version of the importable `gpiod` package, None when there is none (a failing import counts as none)."""
    try:
        import gpiod  # noqa: PLC0415 - needed only on a Pi 5
    except ImportError:
        return None
    return str(getattr(gpiod, "__version__", "0"))


def gpiod_new_enough(version: str | None) -> bool:
    """Whether a `gpiod` version is at least GPIOD_MINIMUM (Bookworm's 1.6 is the old v1 API)."""
    if version is None:
        return False
    parts = []
    for part in version.split(".")[:2]:
        digits = "".join(c for c in part if c.isdigit()) if part[:1].isdigit() else ""
        parts.append(int(digits) if digits else 0)
    return tuple(parts) >= GPIOD_MINIMUM


def _require_gpiod() -> None:
    """Raise GpioUnavailableError, with the fix, when the `gpiod` package is not installed."""
    if importlib.util.find_spec("gpiod") is None:
        raise GpioUnavailableError(
            "the gpiod back-end needs the Python package gpiod >= 2.2 (libgpiod v2): pip install 'robotd[pi5]'"
        )


def find_gpio_chip(label: str = RP1_GPIO_LABEL, dev: str = "/dev") -> str:
    """The path of the GPIO chip labelled `label` under `dev`; GpioUnavailableError when there is none."""
    _require_gpiod()
    import gpiod  # noqa: PLC0415 - needed only on a Pi 5; see the module docstring

    seen = []
    for path in sorted(glob.glob(os.path.join(dev, "gpiochip*"))):
        if not gpiod.is_gpiochip_device(path):
            continue
        try:
            with gpiod.Chip(path) as chip:
                found = chip.get_info().label
        except OSError as error:
            seen.append(f"{path}: {error.strerror}")
            continue
        if found == label:
            return path
        seen.append(f"{path}: {found}")
    raise GpioUnavailableError(
        f"no GPIO chip labelled {label!r} in {dev} ({'; '.join(seen) or 'no GPIO chips'}); "
        "the gpiod back-end is for a Raspberry Pi 5 (use gpio.backend: pigpio elsewhere)"
    )


def _unavailable(what: str, chip: str, offsets: Sequence[int], error: OSError) -> GpioUnavailableError:
    if error.errno == errno.EBUSY:
        hint = "another process holds them (gpioinfo shows which; is a second robotd or pigpiod running?)"
    elif error.errno in (errno.EACCES, errno.EPERM):
        hint = "permission denied: add the service user to the gpio group"
    else:
        hint = error.strerror or str(error)
    unavailable = GpioUnavailableError(f"cannot request {what} {list(offsets)} on {chip}: {hint}")
    unavailable.errno = error.errno  # the kernel's reason, for a caller that waits for busy lines
    return unavailable


class _GpiodEventLines:
    """EventLines on a real gpiod.LineRequest."""

    def __init__(self, request: gpiod.LineRequest, offsets: Sequence[int]) -> None:
        self._request = request
        self._offsets = list(offsets)

    @property
    def fd(self) -> int:
        return self._request.fd

    def levels(self) -> int:
        from gpiod.line import Value  # noqa: PLC0415

        values = self._request.get_values(self._offsets)
        return sum(1 << line for line, value in zip(self._offsets, values, strict=True) if value == Value.ACTIVE)

    def release(self) -> None:
        self._request.release()


def open_event_lines(offsets: Sequence[int], settings: EventLineSettings) -> EventLines:
    """One request for all `offsets`: inputs, both edges, CLOCK_MONOTONIC stamps, the kernel buffer of `settings`."""
    _require_gpiod()
    import gpiod  # noqa: PLC0415
    from gpiod.line import Bias, Clock, Direction, Edge  # noqa: PLC0415

    chip = settings.chip or find_gpio_chip()
    bias = {"up": Bias.PULL_UP, "down": Bias.PULL_DOWN, "off": Bias.DISABLED}[settings.pull]
    line_settings = gpiod.LineSettings(
        direction=Direction.INPUT,
        edge_detection=Edge.BOTH,
        bias=bias,
        debounce_period=timedelta(microseconds=settings.debounce_us),
        event_clock=Clock.MONOTONIC,
    )
    try:
        request = gpiod.request_lines(
            chip,
            config={tuple(offsets): line_settings},
            consumer=settings.consumer,
            event_buffer_size=settings.event_buffer_size,
        )
    except OSError as error:
        raise _unavailable("encoder lines", chip, offsets, error) from error
    return _GpiodEventLines(request, offsets)


class _GpiodOutputLines:
    """OutputLines on a real gpiod.LineRequest."""

    def __init__(self, request: gpiod.LineRequest) -> None:
        self._request = request

    def set_values(self, values: Mapping[int, int]) -> None:
        from gpiod.line import Value  # noqa: PLC0415

        self._request.set_values({line: Value.ACTIVE if level else Value.INACTIVE for line, level in values.items()})

    def release(self) -> None:
        self._request.release()


def open_output_lines(offsets: Sequence[int], chip: str | None = None) -> OutputLines:
    """One request for all `offsets` as push-pull outputs, driven low from the start."""
    _require_gpiod()
    import gpiod  # noqa: PLC0415
    from gpiod.line import Direction, Value  # noqa: PLC0415

    path = chip or find_gpio_chip()
    settings = gpiod.LineSettings(direction=Direction.OUTPUT, output_value=Value.INACTIVE)
    try:
        request = gpiod.request_lines(path, config={tuple(offsets): settings}, consumer="robotd-motors")
    except OSError as error:
        raise _unavailable("motor direction lines", path, offsets, error) from error
    return _GpiodOutputLines(request)


def read_line_holders(offsets: Sequence[int], chip: str | None = None) -> tuple[str, LineHolders]:
    """The chip's path and who holds each of `offsets` (the kernel's line info; nothing is requested)."""
    _require_gpiod()
    import gpiod  # noqa: PLC0415

    path = chip or find_gpio_chip()
    try:
        with gpiod.Chip(path) as opened:
            infos = {offset: opened.get_line_info(offset) for offset in offsets}
    except OSError as error:
        raise _unavailable("the line info of", path, offsets, error) from error
    return path, {offset: (info.consumer or "") if info.used else None for offset, info in infos.items()}
