"""Motor outputs: each L298 channel (enable PWM, two direction inputs) through gpiozero on pigpiod.

Duty in [-1, 1] per wheel (FL, FR, RL, RR): the sign picks the direction inputs (IN1 high = forward), the
magnitude is the enable pin's PWM duty, after the wheel's sign and the configured limit. Zero duty lets the motor
coast (enable low, both inputs low). Every path out zeroes the motors: `GpiozeroMotors` starts at zero, `close()`
and leaving its `with` block (normally or by an exception) zero it, and `stop_all_motors` does it from another
process after a crash.

Back-end seam: the daemon depends only on `MotorOutputs`; an lgpio back-end (Pi 5, Raspberry Pi OS 13) would be a
second class with the same three methods.
"""

from __future__ import annotations

import contextlib
import math
import signal
from collections.abc import Iterator
from types import FrameType, TracebackType
from typing import Any, Protocol, Self

from drivers.pigpio_link import PigpiodUnavailableError, probe
from robotd.config import WHEELS, MotorPins, MotorsConfig, PigpiodConfig

Duties = tuple[float, float, float, float]


class MotorOutputs(Protocol):
    """What the daemon needs from a motor back-end."""

    def set_duties(self, duties: Duties) -> None:
        """Apply one duty per wheel, each in [-1, 1] (clamped to the configured limit)."""
        ...

    def zero(self) -> None:
        """Stop every motor (coast)."""
        ...

    def close(self) -> None:
        """Zero the motors and release the pins."""
        ...


def wheel_pins(motors: MotorsConfig) -> list[MotorPins]:
    """The motors' pins in wheel order."""
    return [getattr(motors.wheels, wheel) for wheel in WHEELS]


def command_duty(duty: float, sign: int, limit: float) -> float:
    """The duty to apply: wheel sign applied, clamped to [-limit, limit]; not-a-number stops the wheel."""
    if not math.isfinite(duty):
        return 0.0
    return max(-limit, min(limit, duty * sign))


class _Channel:
    """One L298 channel; remembers what it last sent so an unchanged duty costs no round trip to pigpiod."""

    def __init__(self, pins: MotorPins, frequency_hz: int, factory: Any) -> None:
        from gpiozero import DigitalOutputDevice, PWMOutputDevice  # noqa: PLC0415 - gpiozero is slow to import

        self.devices: list[Any] = []
        self.enable = self._add(PWMOutputDevice(pins.enable, frequency=frequency_hz, pin_factory=factory))
        self.in1 = self._add(DigitalOutputDevice(pins.in1, initial_value=False, pin_factory=factory))
        self.in2 = self._add(DigitalOutputDevice(pins.in2, initial_value=False, pin_factory=factory))
        self.direction = 0
        self.magnitude = 0.0

    def _add(self, device: Any) -> Any:
        self.devices.append(device)
        return device

    def apply(self, duty: float) -> None:
        direction = (duty > 0) - (duty < 0)
        magnitude = abs(duty)
        if direction != self.direction:
            # Enable off before the inputs change: never drive the bridge through a half-switched state.
            if self.magnitude:
                self.enable.value = 0.0
                self.magnitude = 0.0
            self.in1.value = direction > 0
            self.in2.value = direction < 0
            self.direction = direction
        if magnitude != self.magnitude:
            self.enable.value = magnitude
            self.magnitude = magnitude


class GpiozeroMotors:
    """The four L298 channels on gpiozero's PiGPIOFactory; a context manager that zeroes the motors on exit."""

    def __init__(self, motors: MotorsConfig, pigpiod: PigpiodConfig) -> None:
        # pigpio's client prints a banner and hands back a dead connection when pigpiod is absent: ask first.
        probe(pigpiod.host, pigpiod.port, pigpiod.connect_timeout_s)
        from gpiozero.pins.pigpio import PiGPIOFactory  # noqa: PLC0415 - gpiozero is slow to import

        self._motors = motors
        self._factory: Any = PiGPIOFactory(host=pigpiod.host, port=pigpiod.port)
        self._channels: list[_Channel] = []
        try:
            for pins in wheel_pins(motors):
                self._channels.append(_Channel(pins, motors.pwm_frequency_hz, self._factory))
        except BaseException:
            self.close()
            raise
        self._signs = [pins.sign for pins in wheel_pins(motors)]

    def set_duties(self, duties: Duties) -> None:
        """Apply one duty per wheel in [-1, 1]; a failure zeroes every motor before it propagates."""
        try:
            for channel, duty, sign in zip(self._channels, duties, self._signs, strict=True):
                channel.apply(command_duty(duty, sign, self._motors.duty_limit))
        except BaseException:
            self.zero()
            raise

    def zero(self) -> None:
        """Stop every motor (coast): enable at 0, both inputs low; every pin is written, whatever was cached."""
        for channel in self._channels:
            with contextlib.suppress(Exception):  # zero the others even if one pin fails
                channel.enable.value = 0.0
                channel.magnitude = 0.0
                channel.in1.off()
                channel.in2.off()
                channel.direction = 0

    def close(self) -> None:
        """Zero the motors, release the pins and disconnect."""
        self.zero()
        for channel in self._channels:
            for device in channel.devices:
                device.close()
        self._channels = []
        if self._factory is not None:
            self._factory.close()
            self._factory = None

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None
    ) -> None:
        self.close()


def stop_all_motors(motors: MotorsConfig, pigpiod: PigpiodConfig) -> None:
    """Drive every motor pin low through pigpiod, without the daemon (blocking; for systemd's ExecStopPost).

    This uses pigpio directly, not gpiozero: gpiozero returns its pins to inputs when it closes, which would leave
    the L298 inputs floating after this process exits; pigpio's write leaves them outputs driven low.
    """
    import pigpio  # noqa: PLC0415 - only this path needs the raw client

    probe(pigpiod.host, pigpiod.port, pigpiod.connect_timeout_s)
    pi: Any = pigpio.pi(pigpiod.host, pigpiod.port, show_errors=False)
    if not pi.connected:
        raise PigpiodUnavailableError(pigpiod.host, pigpiod.port, "pigpio client could not connect")
    try:
        for pins in wheel_pins(motors):
            for gpio in (pins.enable, pins.in1, pins.in2):
                pi.write(gpio, 0)  # also stops PWM on the pin
    finally:
        pi.stop()


@contextlib.contextmanager
def termination_as_exit() -> Iterator[None]:
    """Within this block SIGTERM and SIGHUP raise SystemExit, so `with` blocks and `finally` clauses run.

    For blocking programs on the main thread (the daemon has its own asyncio signal handlers).
    """

    def exit_on_signal(signum: int, _frame: FrameType | None) -> None:
        raise SystemExit(128 + signum)

    previous = {sig: signal.signal(sig, exit_on_signal) for sig in (signal.SIGTERM, signal.SIGHUP)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
