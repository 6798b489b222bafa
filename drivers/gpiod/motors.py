"""Motor outputs on a Raspberry Pi 5: each L298 enable on an RP1 hardware PWM channel, the direction inputs on one
libgpiod output request.

Same contract as the pigpio back-end (drivers.wheels.motors): duty in [-1, 1] per wheel (FL, FR, RL, RR), the sign
picks the direction inputs (IN1 high = forward), the magnitude is the enable's PWM duty after the wheel's sign and the
limit; zero duty coasts (duty 0, both inputs low). The bridge rule: a wheel whose direction changes has its enable at
duty 0 before its inputs change, never driven through a half-switched bridge. All direction changes of one command go
out in one `set_values` call, then the new duties.

Every path out zeroes the motors: `GpiodMotors` starts at zero; `close()` and leaving its `with` block zero them,
disable and unexport the channels; a failing `set_duties` zeroes before it raises. Because sysfs PWM outlives its
process, a watchdog process (drivers.gpiod.watchdog) stops the channels when this process dies without closing, and,
given `heartbeat_timeout_s`, when its heartbeats stop (drivers.gpiod.deadman bumps it); `stop_gpiod_motors` does the
same from `robotd stop-motors` (systemd's ExecStopPost).
"""

from __future__ import annotations

import contextlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Self

from drivers.gpiod.lines import OutputLines, OutputLinesOpener, open_output_lines
from drivers.gpiod.pwm import (
    PWM_CLASS,
    RP1_PWM_DEVICE,
    SYSFS,
    Attributes,
    PwmChannel,
    find_pwm_chip,
    pwm_channel_of,
    stop_pwm_channels,
)
from drivers.gpiod.watchdog import PwmWatchdog
from drivers.settings import MotorPinsLike
from drivers.wheels.motors import Duties, command_duty


class _Wheel:
    """One wheel's channel and what was last written to it."""

    def __init__(self, wiring: MotorPinsLike, pwm: PwmChannel) -> None:
        self.in1, self.in2, self.sign = wiring.in1, wiring.in2, wiring.sign
        self.pwm = pwm
        self.direction = 0


class GpiodMotors:
    """The four L298 channels on RP1 PWM and libgpiod (see the module docstring); a `MotorOutputs`."""

    def __init__(
        self,
        wheels: Sequence[MotorPinsLike],
        *,
        frequency_hz: float,
        duty_limit: float,
        pwm_chip: Path | None = None,
        attributes: Attributes = SYSFS,
        open_outputs: OutputLinesOpener = open_output_lines,
        gpio_chip: str | None = None,
        watchdog: bool = True,
        heartbeat_timeout_s: float | None = None,
    ) -> None:
        if len(wheels) != 4:
            raise ValueError(f"four motors (FL, FR, RL, RR) are needed, got {len(wheels)}")
        channels = [pwm_channel_of(wiring.enable) for wiring in wheels]
        if len(set(channels)) != 4:
            raise ValueError(f"each motor needs its own PWM channel, enable pins {[w.enable for w in wheels]}")
        self._duty_limit = duty_limit
        self._wheels: list[_Wheel] = []
        self._outputs: OutputLines | None = None
        self._watchdog: PwmWatchdog | None = None
        chip = pwm_chip or find_pwm_chip()
        try:
            self._outputs = open_outputs([line for w in wheels for line in (w.in1, w.in2)], gpio_chip)
            for wiring, channel in zip(wheels, channels, strict=True):
                pwm = PwmChannel(chip, channel, attributes)
                self._wheels.append(_Wheel(wiring, pwm))
                pwm.open(frequency_hz)
            if watchdog:
                self._watchdog = PwmWatchdog(
                    chip,
                    channels,
                    timeout_s=heartbeat_timeout_s,
                    direction_pins=[line for w in wheels for line in (w.in1, w.in2)],
                    gpio_chip=gpio_chip,
                )
        except BaseException:
            self.close()
            raise

    @property
    def watchdog(self) -> PwmWatchdog | None:
        """The watchdog process guarding these motors (a deadman when `heartbeat_timeout_s` was given), or None."""
        return self._watchdog

    def set_duties(self, duties: Duties) -> None:
        """Apply one duty per wheel in [-1, 1]; a failure zeroes every motor before it propagates."""
        try:
            targets = [
                command_duty(duty, wheel.sign, self._duty_limit)
                for wheel, duty in zip(self._wheels, duties, strict=True)
            ]
            self._write(targets)
        except BaseException:
            self.zero()
            raise

    def _write(self, targets: list[float]) -> None:
        assert self._outputs is not None
        inputs: dict[int, int] = {}
        for wheel, duty in zip(self._wheels, targets, strict=True):
            direction = (duty > 0) - (duty < 0)
            if direction == wheel.direction:
                continue
            # Enable off before the inputs change: never drive the bridge through a half-switched state.
            wheel.pwm.set_duty(0.0)
            inputs[wheel.in1], inputs[wheel.in2] = int(direction > 0), int(direction < 0)
            wheel.direction = direction
        if inputs:
            self._outputs.set_values(inputs)
        for wheel, duty in zip(self._wheels, targets, strict=True):
            wheel.pwm.set_duty(abs(duty))

    def zero(self) -> None:
        """Stop every motor (coast): every enable at duty 0, then every input low, whatever was cached."""
        for wheel in self._wheels:
            with contextlib.suppress(Exception):  # zero the others even if one channel fails
                wheel.pwm.set_duty(0.0, force=True)
        if self._outputs is not None:
            with contextlib.suppress(Exception):
                self._outputs.set_values({line: 0 for w in self._wheels for line in (w.in1, w.in2)})
        for wheel in self._wheels:
            wheel.direction = 0

    def close(self) -> None:
        """Zero the motors, disable and unexport the channels, stop the watchdog, release the lines."""
        self.zero()
        for wheel in self._wheels:
            with contextlib.suppress(Exception):  # each on its own: one failure must not leave the rest running
                wheel.pwm.close()
        self._wheels = []
        if self._watchdog is not None:
            self._watchdog.stop()
            self._watchdog = None
        if self._outputs is not None:
            with contextlib.suppress(Exception):
                self._outputs.release()
            self._outputs = None

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None
    ) -> None:
        self.close()


@dataclass(frozen=True, slots=True)
class StopReport:
    """What `stop_gpiod_motors` could not do, one line each."""

    pwm_problems: list[str]
    """PWM attributes that could not be written: those channels may still run."""
    direction_note: str | None
    """Why the direction pins were left as they are (held by a running robotd, or no GPIO chip), or None."""


def stop_gpiod_motors(
    enable_pins: Sequence[int],
    direction_pins: Sequence[int] = (),
    *,
    pwm_root: str | Path = PWM_CLASS,
    pwm_device: str = RP1_PWM_DEVICE,
    attributes: Attributes = SYSFS,
    open_outputs: OutputLinesOpener = open_output_lines,
    gpio_chip: str | None = None,
) -> StopReport:
    """Stop the motors without robotd (blocking; for `robotd stop-motors` and systemd's ExecStopPost).

    Every exported RP1 PWM channel of `enable_pins` gets duty 0 then enable 0; then, if no process holds them, the
    direction pins are driven low. Raises GpioUnavailableError when there is no RP1 PWM chip. Direction pins held by
    a running robotd are not an error here (its own exit path owns them; with every enable at 0 the L298 coasts).
    """
    chip = find_pwm_chip(pwm_device, pwm_root)
    problems = stop_pwm_channels(chip, [pwm_channel_of(pin) for pin in enable_pins], attributes)
    note = None
    if direction_pins:
        try:
            outputs = open_outputs(list(direction_pins), gpio_chip)
        except OSError as error:  # GpioUnavailableError is one
            note = f"direction pins left as they are: {error}"
        else:
            try:
                outputs.set_values(dict.fromkeys(direction_pins, 0))
            finally:
                outputs.release()
    return StopReport(problems, note)
