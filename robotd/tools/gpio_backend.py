"""The doctor's view of a GPIO back-end: reachable or not, each pin's mode, one wheel driven at a time, the counts.

One `GpioBackend` per back-end, by the name the configuration chooses it by: `pigpio` (pigpiod through the real
pigpio client, robotd.tools.doctor_pigpio) and `gpiod` (a Pi 5: libgpiod and the RP1's sysfs PWM,
robotd.tools.doctor_gpiod).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from contextlib import AbstractAsyncContextManager
from dataclasses import dataclass
from typing import Protocol

from robotd.config.model import RobotdConfig

Counts = tuple[int, int, int, int]


class BackendUnavailableError(Exception):
    """The back-end does not answer; `fix` says what to do."""

    def __init__(self, detail: str, fix: str) -> None:
        super().__init__(detail)
        self.detail, self.fix = detail, fix


class WheelDrive(Protocol):
    """The motors, one wheel at a time (blocking calls; the doctor runs them off the event loop)."""

    def drive(self, wheel: int, duty: float) -> None:
        """Drive wheel `wheel` (wheel order) at a forward duty in [-1, 1]; every other motor off."""
        ...

    def stop(self) -> None:
        """Every motor off."""
        ...

    def close(self) -> None:
        """Every motor off, then release the back-end."""
        ...


@dataclass(frozen=True, slots=True)
class GpioBackend:
    """What the doctor needs from a back-end (each callable raises BackendUnavailableError when it is not there)."""

    name: str
    reach: Callable[[RobotdConfig], str]
    """Contact the back-end; returns what answered, in words."""
    pin_modes: Callable[[RobotdConfig, Sequence[int]], dict[int, str]] | None
    """Each pin's present function: 'input', 'output', or 'alt0'...'alt5' when a peripheral (I2C, SPI, UART) has it;
    None when the back-end cannot read them."""
    open_drive: Callable[[RobotdConfig], WheelDrive]
    open_counts: Callable[[RobotdConfig], AbstractAsyncContextManager[Callable[[], Counts]]]
    """While open, a function reading the four wheels' cumulative encoder counts (configured signs applied)."""
    pwm_pins: frozenset[int] | None = None
    """The only GPIOs its motor enable (PWM) pins can use; None: any."""
    pin_holders: Callable[[RobotdConfig, Sequence[int]], dict[int, str | None]] | None = None
    """Who holds each pin now (the consumer's name, None when free); None when the back-end cannot tell."""


BACKEND_NAMES = ("pigpio", "gpiod")
"""The names `backends()` answers to, known without importing any back-end (for the command line)."""


def backends() -> dict[str, GpioBackend]:
    """Every back-end the doctor knows, by name."""
    from robotd.tools.doctor_gpiod import gpiod_backend  # noqa: PLC0415 - libgpiod is imported only when used
    from robotd.tools.doctor_pigpio import PIGPIO  # noqa: PLC0415 - the pigpio client is imported only when used

    return {PIGPIO.name: PIGPIO, "gpiod": gpiod_backend()}
