"""A temporary directory laid out as /sys/class/pwm on a Raspberry Pi 5, with the kernel's rules for its writes.

Theory of operation: `root/class/pwm/pwmchipN` are links into `root/devices/platform/axi/1000120000.pcie/<device>/
pwm/pwmchipN`, as sysfs lays them out: the RP1's PWM0 (`1f00098000.pwm`) and, as a decoy with a lower number, its
PWM1 (`1f0009c000.pwm`, the fan's), so a driver that picks a chip by number rather than by device path picks wrong.
Attribute files hold their values as text. The object is the `Attributes` of drivers.gpiod.pwm: a write is checked
as the kernel checks it (export creates `pwmK/` with period, duty_cycle, enable and polarity; duty above period,
enabling with period 0, changing polarity while enabled, a bad number and exporting twice are refused with the
kernel's errno), stored in the file and recorded in `journal`, in order, as {"pwmK/attribute": value}. Another
process may use the real `SysfsAttributes` on the same directory: its writes change the files, unchecked.

Not modelled: the waveform and the pin mux; the kernel's rounding of period and duty to the RP1's clock; udev's
permission change after export beyond refusing the first `settle_writes` writes to a new channel with EACCES;
`capture`, `npwm` other than 4, sysfs's single-write and file-offset rules; what unexport does to the pin.
"""

from __future__ import annotations

import errno
import os
import shutil
import time
from pathlib import Path

DEVICES = Path("devices/platform/axi/1000120000.pcie")
RP1_PWM0 = "1f00098000.pwm"
RP1_PWM1 = "1f0009c000.pwm"
CHANNEL_FILES = {"period": "0", "duty_cycle": "0", "enable": "0", "polarity": "normal"}

Journal = list[dict[str, str]]


def _refuse(code: int, path: Path) -> OSError:
    return OSError(code, os.strerror(code), str(path))


class VirtualPwmSysfs:
    """PWM chips in a directory (see the module docstring); `class_root` stands for /sys/class/pwm."""

    def __init__(
        self, root: Path, *, chip_number: int = 2, settle_writes: int = 0, journal: Journal | None = None
    ) -> None:
        self.root = root
        self.class_root = root / "class" / "pwm"
        self.class_root.mkdir(parents=True, exist_ok=True)
        self.journal: Journal = journal if journal is not None else []
        self.settle_writes = settle_writes
        self._refusals: dict[Path, int] = {}
        self.chip = self._add_chip(RP1_PWM0, chip_number)
        """The RP1 PWM0 chip as the driver should find it: class_root/pwmchipN."""
        self._add_chip(RP1_PWM1, 0)

    @classmethod
    def existing(cls, root: Path, *, chip_number: int = 2) -> VirtualPwmSysfs:
        """A view of the directory another process's stand-in laid out at `root` (nothing created or changed)."""
        view = cls.__new__(cls)
        view.root, view.class_root = root, root / "class" / "pwm"
        view.journal, view.settle_writes, view._refusals = [], 0, {}
        view.chip = view.class_root / f"pwmchip{chip_number}"
        return view

    def _add_chip(self, device: str, number: int) -> Path:
        target = self.root / DEVICES / device / "pwm" / f"pwmchip{number}"
        target.mkdir(parents=True, exist_ok=True)
        for name, value in (("export", ""), ("unexport", ""), ("npwm", "4")):
            (target / name).write_text(value + "\n")
        link = self.class_root / f"pwmchip{number}"
        link.symlink_to(os.path.relpath(target, self.class_root))
        return link

    # --- Attributes --------------------------------------------------------------------------------------------

    def read(self, path: Path) -> str:
        """The attribute's value, stripped (read again while another process's write has emptied the file)."""
        for _ in range(1000):
            value = path.read_text(encoding="ascii").strip()
            if value or path.name in ("export", "unexport"):
                return value
            time.sleep(0.001)  # a plain file is truncated before it is written: sysfs never shows that moment
        return value

    def write(self, path: Path, value: str) -> None:
        """Apply a write as the kernel would; OSError with the kernel's errno when it would refuse."""
        real = Path(os.path.realpath(path))
        if self.root.resolve() not in real.parents:
            raise ValueError(f"{path} is not in this stand-in's directory {self.root}")
        text = value.strip()
        if real.name in ("export", "unexport"):
            self._export(real.parent, text, export=real.name == "export")
            key = real.name
        else:
            channel_dir = real.parent
            if not channel_dir.is_dir():
                raise _refuse(errno.ENOENT, path)
            if self._refusals.get(channel_dir, 0) > 0:
                self._refusals[channel_dir] -= 1
                raise _refuse(errno.EACCES, path)
            self._attribute(channel_dir, real.name, text)
            key = f"{channel_dir.name}/{real.name}"
        self.journal.append({key: text})

    def _export(self, chip: Path, text: str, *, export: bool) -> None:
        if not text.isdigit():
            raise _refuse(errno.EINVAL, chip)
        channel = int(text)
        if channel >= int(self.read(chip / "npwm")):
            raise _refuse(errno.ENODEV, chip)
        channel_dir = chip / f"pwm{channel}"
        if export:
            if channel_dir.exists():
                raise _refuse(errno.EBUSY, channel_dir)
            channel_dir.mkdir()
            for name, initial in CHANNEL_FILES.items():
                (channel_dir / name).write_text(initial + "\n")
            self._refusals[channel_dir] = self.settle_writes
        else:
            if not channel_dir.exists():
                raise _refuse(errno.ENODEV, channel_dir)
            shutil.rmtree(channel_dir)

    def _attribute(self, channel_dir: Path, name: str, text: str) -> None:
        state = {n: self.read(channel_dir / n) for n in CHANNEL_FILES}
        enabled, period, duty = state["enable"] == "1", int(state["period"]), int(state["duty_cycle"])
        if name in ("period", "duty_cycle"):
            if not text.isdigit():
                raise _refuse(errno.EINVAL, channel_dir / name)
            number = int(text)
            new_period, new_duty = (number, duty) if name == "period" else (period, number)
            if new_duty > new_period or (enabled and new_period == 0):
                raise _refuse(errno.EINVAL, channel_dir / name)
        elif name == "enable":
            if text not in ("0", "1") or (text == "1" and period == 0):
                raise _refuse(errno.EINVAL, channel_dir / name)
        elif name == "polarity":
            if text not in ("normal", "inversed"):
                raise _refuse(errno.EINVAL, channel_dir / name)
            if enabled and text != state["polarity"]:
                raise _refuse(errno.EBUSY, channel_dir / name)
        else:
            raise _refuse(errno.EACCES, channel_dir / name)  # read-only or absent
        (channel_dir / name).write_text(text + "\n")

    # --- for tests ---------------------------------------------------------------------------------------------

    def exported(self) -> list[int]:
        """The RP1 PWM0 channels exported now."""
        return sorted(int(p.name[3:]) for p in self.chip.glob("pwm[0-9]*"))

    def output(self, channel: int) -> float:
        """What the channel's pin carries: duty / period while enabled, else 0 (also when not exported)."""
        channel_dir = self.chip / f"pwm{channel}"
        try:
            if self.read(channel_dir / "enable") != "1":
                return 0.0
            return int(self.read(channel_dir / "duty_cycle")) / int(self.read(channel_dir / "period"))
        except FileNotFoundError:  # not exported, or being exported or unexported by another thread right now
            return 0.0
