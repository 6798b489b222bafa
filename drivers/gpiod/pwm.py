"""The RP1's hardware PWM through sysfs (/sys/class/pwm), and the stop that needs no running robotd.

Theory of operation: the chip is found by its device path (`1f00098000.pwm`, the RP1's PWM0), never by its number,
which changed between kernels: /sys/class/pwm/pwmchipN is a link into the device tree and the chip is the one whose
target passes through that device. A channel is exported by writing its number to `export`, which creates `pwmK/`
with `period`, `duty_cycle` (nanoseconds), `polarity` and `enable`; udev then hands the files to the gpio group, a
moment later, so the first writes are retried for up to a second. Each attribute is written with one `write()`, as
sysfs requires. A duty can never exceed the period (the kernel refuses it), so a channel is set up with duty 0 first.

Channels on the header: GPIO 12 -> 0, 13 -> 1, 18 -> 2, 19 -> 3 (RP1 datasheet: PWM0_CHAN0..3; ALT0 on 12 and 13,
ALT3 on 18 and 19). sysfs PWM does not switch the pins to that function: a device-tree overlay must (or `pinctrl set
12 a0` for a test). The overlay lines for all four are an estimate to confirm on a board; for GPIO 12 and 13,
`dtoverlay=pwm-2chan,pin=12,func=4,pin2=13,func2=4` (func 4 = ALT0, 2 = ALT3 in the overlay's numbering).

Safety: sysfs PWM keeps running after the process that set it dies. `stop_pwm_channels` writes duty 0 then enable 0
on every exported channel from any process (systemd's ExecStopPost, `robotd stop-motors`, the watchdog in
drivers.gpiod.watchdog); duty 0 comes first because a disabled channel's pin level is up to the driver, while duty 0
is low on every driver (normal polarity).
"""

from __future__ import annotations

import errno
import os
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Protocol

from drivers.gpiod.lines import GpioUnavailableError

RP1_PWM_DEVICE = "1f00098000.pwm"
PWM_CLASS = "/sys/class/pwm"
RP1_PWM_CHANNELS = {12: 0, 13: 1, 18: 2, 19: 3}
"""BCM GPIO -> channel of the RP1's PWM0."""
SETTLE_S = 1.0
"""How long a freshly exported channel may refuse writes while udev sets its permissions."""


class Attributes(Protocol):
    """Reads and writes sysfs attribute files (the stand-in in drivers.virtual.pwm_sysfs applies the kernel's rules)."""

    def write(self, path: Path, value: str) -> None:
        """Write `value` to the attribute in one call; OSError as the kernel answers."""
        ...

    def read(self, path: Path) -> str:
        """The attribute's value, stripped."""
        ...


class SysfsAttributes:
    """Attributes of the real sysfs: one unbuffered write per value."""

    def write(self, path: Path, value: str) -> None:
        """Write `value` with one write(2) (O_TRUNC as a shell's `>` opens it: sysfs ignores it, a file needs it)."""
        fd = os.open(path, os.O_WRONLY | os.O_TRUNC)
        try:
            os.write(fd, value.encode())
        finally:
            os.close(fd)

    def read(self, path: Path) -> str:
        """The attribute's value, stripped."""
        return path.read_text(encoding="ascii").strip()


SYSFS = SysfsAttributes()


def find_pwm_chip(device: str = RP1_PWM_DEVICE, root: str | Path = PWM_CLASS) -> Path:
    """The pwmchipN under `root` whose link leads through `device`; GpioUnavailableError when none does."""
    seen = []
    for chip in sorted(Path(root).glob("pwmchip*")):
        target = Path(os.path.realpath(chip))
        if device in target.parts:
            return chip
        seen.append(f"{chip.name} -> {target.parent.parent.name}")
    raise GpioUnavailableError(
        f"no PWM chip of device {device} under {root} ({'; '.join(seen) or 'no PWM chips'}); on a Raspberry Pi 5 "
        "enable the RP1's PWM with a dtoverlay in /boot/firmware/config.txt (see drivers.gpiod.pwm) and reboot"
    )


def pwm_channel_of(gpio: int) -> int:
    """The RP1 PWM0 channel of a header GPIO; ValueError for a GPIO without one."""
    if gpio not in RP1_PWM_CHANNELS:
        raise ValueError(f"GPIO {gpio} has no RP1 hardware PWM: enable pins must be among {sorted(RP1_PWM_CHANNELS)}")
    return RP1_PWM_CHANNELS[gpio]


class PwmChannel:
    """One exported channel: period set once, duty written only when it changes."""

    def __init__(
        self,
        chip: Path,
        channel: int,
        attributes: Attributes = SYSFS,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        self.chip = chip
        self.channel = channel
        self.path = chip / f"pwm{channel}"
        self._attributes = attributes
        self._sleep = sleep
        self.period_ns = 0
        self.duty_ns = 0

    def open(self, frequency_hz: float) -> None:
        """Export the channel (or take it over from a process that died), duty 0, set the period, enable it."""
        if not self.path.is_dir():
            try:
                self._attributes.write(self.chip / "export", str(self.channel))
            except OSError as error:
                if error.errno != errno.EBUSY:  # EBUSY: exported meanwhile, by us before a crash
                    raise
        self.period_ns = round(1e9 / frequency_hz)
        self._settled_write("duty_cycle", "0")
        self.duty_ns = 0
        self._attributes.write(self.path / "period", str(self.period_ns))
        if self._attributes.read(self.path / "polarity") != "normal":
            self._attributes.write(self.path / "enable", "0")  # polarity changes only while disabled
            self._attributes.write(self.path / "polarity", "normal")
        self._attributes.write(self.path / "enable", "1")

    def _settled_write(self, name: str, value: str) -> None:
        """The first write after export: retried while udev has not yet given the files to the gpio group."""
        deadline = time.monotonic() + SETTLE_S
        while True:
            try:
                self._attributes.write(self.path / name, value)
                return
            except (PermissionError, FileNotFoundError):
                if time.monotonic() > deadline:
                    raise
                self._sleep(0.01)

    def set_duty(self, fraction: float, *, force: bool = False) -> None:
        """Duty as a fraction of the period, in [0, 1] (truncated to whole nanoseconds); skipped when unchanged
        unless `force`."""
        duty_ns = int(min(1.0, max(0.0, fraction)) * self.period_ns)
        if force or duty_ns != self.duty_ns:
            self._attributes.write(self.path / "duty_cycle", str(duty_ns))
            self.duty_ns = duty_ns

    def stop(self) -> None:
        """Duty 0, then disabled: both written whatever was cached, the second even if the first fails."""
        try:
            self._attributes.write(self.path / "duty_cycle", "0")
            self.duty_ns = 0
        finally:
            self._attributes.write(self.path / "enable", "0")

    def close(self) -> None:
        """Stop, then unexport."""
        try:
            self.stop()
        finally:
            self._attributes.write(self.chip / "unexport", str(self.channel))


def stop_pwm_channels(chip: Path, channels: Iterable[int], attributes: Attributes = SYSFS) -> list[str]:
    """Duty 0 and enable 0 on each exported channel of `channels`; returns what could not be done (one line each).

    A channel that is not exported is not running from sysfs and is left alone.
    """
    problems = []
    for channel in channels:
        path = chip / f"pwm{channel}"
        if not path.is_dir():
            continue
        for name, value in (("duty_cycle", "0"), ("enable", "0")):
            try:
                attributes.write(path / name, value)
            except OSError as error:
                problems.append(f"{path / name}: {error.strerror or error}")
    return problems
