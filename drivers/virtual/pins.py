"""The GPIO pins of a virtual Raspberry Pi 4B as pigpiod sees them: modes, pulls, levels, PWM, glitch filters.

Pure state and rules, no sockets, not thread-safe (the virtual pigpiod holds a lock around it). Each rule is the
documented behaviour of pigpio's C library: writing a level makes a pin an output and stops its PWM; PWM duty is an
integer in [0, range]; a range change rescales an active duty; the PWM frequency snaps to the nearest one pigpio
offers at its default 5 us sample rate, and the "real range" is 200000 / frequency. `written_gpios` says which
GPIOs a command writes, so the server can keep a history of every write (`PinWrite`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from drivers.pigpiod.protocol import Cmd, Command, Err, Mode, Pull

GPIO_COUNT = 54
USER_GPIOS = 32
BANK1 = 0xFFFFFFFF
MAX_GLITCH_US = 300_000
PWM_FREQUENCIES = (8000, 4000, 2000, 1600, 1000, 800, 500, 400, 320, 250, 200, 160, 100, 80, 50, 40, 20, 10)
"""The PWM frequencies pigpio offers at its default 5 us sample rate."""
DEFAULT_PWM_FREQUENCY = 800
DEFAULT_PWM_RANGE = 255


@dataclass(frozen=True, slots=True)
class PinWrite:
    """One GPIO as a write command left it: when (monotonic s), who (socket or script), what, and the pin after."""

    t: float
    source: str
    command: str
    gpio: int
    mode: int
    level: int
    duty: float
    """PWM duty / range of an active PWM, else the level of an output, 0 for an input (as `pwm_fraction`)."""


@dataclass(slots=True)
class Pwm:
    """One GPIO's PWM settings (kept while PWM is off, as pigpio does)."""

    frequency: int = DEFAULT_PWM_FREQUENCY
    range: int = DEFAULT_PWM_RANGE
    duty: int = 0
    active: bool = False


class PinBank:
    """All 54 GPIOs: what the command socket can read and change, and what the simulator drives."""

    def __init__(self) -> None:
        # At power-on GPIO 0-8 are pulled up and the rest pulled down; every pin is an input.
        self.modes = [Mode.INPUT] * GPIO_COUNT
        self.pulls = [Pull.UP if gpio <= 8 else Pull.DOWN for gpio in range(GPIO_COUNT)]
        self.levels = sum(1 << gpio for gpio in range(9))
        self.driven = 0
        """Bits the simulator has driven: their level no longer follows the pull resistor."""
        self.pwm = [Pwm() for _ in range(USER_GPIOS)]
        self.glitch_us = [0] * USER_GPIOS

    @property
    def bank1(self) -> int:
        """Levels of GPIO 0-31."""
        return self.levels & BANK1

    def output_mask(self) -> int:
        """Bits of bank 1 in output mode: the simulator cannot drive them."""
        return sum(1 << gpio for gpio in range(USER_GPIOS) if self.modes[gpio] == Mode.OUTPUT)

    def level(self, gpio: int) -> int:
        """Level of one GPIO (0 or 1)."""
        return (self.levels >> gpio) & 1

    def pwm_fraction(self, gpio: int) -> float:
        """Duty of an active PWM as a fraction of its range; a steady output counts as 0 or 1."""
        pwm = self.pwm[gpio]
        if pwm.active:
            return pwm.duty / pwm.range
        return float(self.level(gpio)) if self.modes[gpio] == Mode.OUTPUT else 0.0

    def written_gpios(self, command: Command) -> list[int]:
        """The GPIOs a command would write (mode, pull, level, PWM duty or range); empty for a read or a bad GPIO."""
        cmd, gpio = command.cmd, command.p1
        if cmd in (Cmd.MODES, Cmd.PUD, Cmd.WRITE):
            return [gpio] if gpio < GPIO_COUNT else []
        if cmd in (Cmd.PWM, Cmd.PRS):
            return [gpio] if gpio < USER_GPIOS else []
        if cmd in (Cmd.BC1, Cmd.BS1, Cmd.BC2, Cmd.BS2):
            shift = 32 if cmd in (Cmd.BC2, Cmd.BS2) else 0
            end = GPIO_COUNT if shift else USER_GPIOS
            # only outputs take a bank write (see _bank_write)
            return [g for g in range(shift, end) if command.p1 >> (g - shift) & 1 and self.modes[g] == Mode.OUTPUT]
        return []

    def write_record(self, gpio: int, t: float, source: str, command: str) -> PinWrite:
        """A GPIO's state now, as a history entry."""
        if gpio < USER_GPIOS:
            duty = self.pwm_fraction(gpio)
        else:
            duty = float(self.level(gpio)) if self.modes[gpio] == Mode.OUTPUT else 0.0
        return PinWrite(t, source, command, gpio, int(self.modes[gpio]), self.level(gpio), duty)

    def execute(self, command: Command) -> int:
        """Carry out a pin command; returns pigpio's result (negative = error)."""
        cmd, gpio, value = command.cmd, command.p1, command.p2
        if cmd in _ANY_GPIO and gpio >= GPIO_COUNT:
            return Err.BAD_GPIO
        if cmd in _USER_GPIO and gpio >= USER_GPIOS:
            return Err.BAD_USER_GPIO
        match cmd:
            case Cmd.MODES:
                return self._set_mode(gpio, value)
            case Cmd.MODEG:
                return int(self.modes[gpio])
            case Cmd.PUD:
                return self._set_pull(gpio, value)
            case Cmd.READ:
                return self.level(gpio)
            case Cmd.WRITE:
                if value > 1:
                    return Err.BAD_LEVEL
                self._write(gpio, value)
                return 0
            case Cmd.PWM:
                return self._set_duty(gpio, value)
            case Cmd.PRS:
                return self._set_range(gpio, value)
            case Cmd.PFS:
                return self._set_frequency(gpio, value)
            case Cmd.GDC:
                return self.pwm[gpio].duty if self.pwm[gpio].active else Err.NOT_PWM_GPIO
            case Cmd.PRG:
                return self.pwm[gpio].range
            case Cmd.PRRG:
                return 200_000 // self.pwm[gpio].frequency
            case Cmd.PFG:
                return self.pwm[gpio].frequency
            case Cmd.FG:
                if value > MAX_GLITCH_US:
                    return Err.BAD_FILTER
                self.glitch_us[gpio] = value
                return 0
            case Cmd.BR1:
                return self.bank1
            case Cmd.BR2:
                return (self.levels >> 32) & 0x3FFFFF
            case Cmd.BC1 | Cmd.BC2 | Cmd.BS1 | Cmd.BS2:
                return self._bank_write(cmd, gpio)
        return Err.UNKNOWN_COMMAND

    def _set_mode(self, gpio: int, mode: int) -> int:
        if mode > Mode.ALT3:
            return Err.BAD_MODE
        self.modes[gpio] = Mode(mode)
        if mode != Mode.OUTPUT:
            self._stop_pwm(gpio)
            if mode == Mode.INPUT:
                self._follow_pull(gpio)
        return 0

    def _set_pull(self, gpio: int, pull: int) -> int:
        if pull > Pull.UP:
            return Err.BAD_PUD
        self.pulls[gpio] = Pull(pull)
        if self.modes[gpio] == Mode.INPUT:
            self._follow_pull(gpio)
        return 0

    def _follow_pull(self, gpio: int) -> None:
        """An input nobody drives reads its pull resistor (a floating one keeps its last level)."""
        if self.driven >> gpio & 1 or self.pulls[gpio] == Pull.OFF:
            return
        self._set_level(gpio, 1 if self.pulls[gpio] == Pull.UP else 0)

    def _write(self, gpio: int, level: int) -> None:
        self.modes[gpio] = Mode.OUTPUT
        self._stop_pwm(gpio)
        self._set_level(gpio, level)

    def _set_level(self, gpio: int, level: int) -> None:
        self.levels = (self.levels | (1 << gpio)) if level else (self.levels & ~(1 << gpio))

    def _stop_pwm(self, gpio: int) -> None:
        if gpio < USER_GPIOS and self.pwm[gpio].active:
            self.pwm[gpio].active = False
            self._set_level(gpio, 0)

    def _set_duty(self, gpio: int, duty: int) -> int:
        pwm = self.pwm[gpio]
        if duty > pwm.range:
            return Err.BAD_DUTYCYCLE
        self.modes[gpio] = Mode.OUTPUT
        pwm.duty, pwm.active = duty, True
        # The pin's level is only modelled at the steady extremes: no PWM edges are generated.
        self._set_level(gpio, 1 if duty == pwm.range else 0)
        return 0

    def _set_range(self, gpio: int, new_range: int) -> int:
        if not 25 <= new_range <= 40_000:
            return Err.BAD_DUTYRANGE
        pwm = self.pwm[gpio]
        if pwm.active:
            pwm.duty = round(pwm.duty * new_range / pwm.range)
        pwm.range = new_range
        return 200_000 // pwm.frequency

    def _set_frequency(self, gpio: int, frequency: int) -> int:
        nearest = min(PWM_FREQUENCIES, key=lambda offered: (abs(offered - frequency), -offered))
        self.pwm[gpio].frequency = nearest
        return nearest

    def _bank_write(self, cmd: int, bits: int) -> int:
        outputs = self.output_mask()
        shift = 32 if cmd in (Cmd.BC2, Cmd.BS2) else 0
        if shift:
            outputs = sum(1 << gpio for gpio in range(32, GPIO_COUNT) if self.modes[gpio] == Mode.OUTPUT)
        touched = (bits << shift) & outputs
        self.levels = (self.levels | touched) if cmd in (Cmd.BS1, Cmd.BS2) else (self.levels & ~touched)
        return 0


_ANY_GPIO = frozenset({Cmd.MODES, Cmd.MODEG, Cmd.PUD, Cmd.READ, Cmd.WRITE})
_USER_GPIO = frozenset({Cmd.PWM, Cmd.PRS, Cmd.PFS, Cmd.GDC, Cmd.PRG, Cmd.PRRG, Cmd.PFG, Cmd.FG})

U32 = npt.NDArray[np.uint32]


def glitch_filter(ticks: U32, words: U32, previous: int, steady_us: dict[int, int]) -> tuple[U32, U32]:
    """Apply pigpio's glitch filter to a batch of bank-1 level changes.

    `words[i]` is bank 1 after the change at `ticks[i]`; `previous` is bank 1 before the batch. A change of a
    filtered GPIO is reported only if its level then holds for `steady_us[gpio]` microseconds, and it is stamped that
    much later, as pigpio does. The last change of a GPIO in the batch is taken as steady (the batch does not know
    the future). Returns the reported (ticks, words): sorted by tick, one report per tick, no report without change.
    """
    changes = words ^ np.concatenate((np.array([previous], dtype=np.uint32), words[:-1]))
    filtered = sum(1 << gpio for gpio, steady in steady_us.items() if steady > 0)
    if not filtered or not np.any(changes & np.uint32(filtered)):
        keep = changes != 0
        return ticks[keep], words[keep]
    # Work in microseconds relative to the first tick: signed 32-bit steps unwrap the 2^32 wrap-around.
    steps = (ticks[1:] - ticks[:-1]).view(np.int32).astype(np.int64)
    delays = {steady for gpio, steady in steady_us.items() if steady > 0 and np.any(changes & np.uint32(1 << gpio))}
    if len(delays) == 1 and not np.any(changes & np.uint32(BANK1 ^ filtered)):
        # The common case (encoder pins, one filter, no glitch): when no two changes are closer than the filter,
        # every change holds long enough, and the filter only stamps each one `steady` later.
        steady = delays.pop()
        keep = changes != 0
        if not len(steps) or int(steps[keep[1:]].min(initial=steady)) >= steady:
            return ticks[keep] + np.uint32(steady), words[keep]
    elapsed = np.concatenate((np.zeros(1, dtype=np.int64), np.cumsum(steps)))
    plain = changes & np.uint32(BANK1 ^ filtered)
    at = np.flatnonzero(plain)
    times, toggles = [elapsed[at]], [plain[at]]
    for gpio, steady in steady_us.items():
        bit = np.uint32(1 << gpio)
        if steady <= 0 or not np.any(changes & bit):
            continue
        at = np.flatnonzero(changes & bit)
        held = np.diff(elapsed[at], append=np.iinfo(np.int64).max)
        stable_at = at[held >= steady]
        stable_levels = (words[stable_at] >> np.uint32(gpio)) & np.uint32(1)
        before = np.concatenate(([(previous >> gpio) & 1], stable_levels[:-1]))
        reported = stable_at[stable_levels != before]
        times.append(elapsed[reported] + steady)
        toggles.append(np.full(len(reported), bit, dtype=np.uint32))
    when = np.concatenate(times)
    toggle = np.concatenate(toggles)
    if len(when) == 0:
        return ticks[:0], words[:0]
    order = np.argsort(when, kind="stable")
    when, toggle = when[order], toggle[order]
    levels = np.uint32(previous) ^ np.bitwise_xor.accumulate(toggle)
    last_of_tick = np.append(when[1:] != when[:-1], True)
    when, levels = when[last_of_tick], levels[last_of_tick]
    changed = levels != np.concatenate((np.array([previous], dtype=np.uint32), levels[:-1]))
    out_ticks = ((when[changed] + int(ticks[0])) & BANK1).astype(np.uint32)
    return out_ticks, levels[changed]
