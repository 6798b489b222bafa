"""Motor outputs: each L298 channel (enable PWM, two direction inputs) through gpiozero on pigpiod.

Duty in [-1, 1] per wheel (FL, FR, RL, RR): the sign picks the direction inputs (IN1 high = forward), the
magnitude is the enable pin's PWM duty, after the wheel's sign and the configured limit. Zero duty lets the motor
coast (enable low, both inputs low). Every path out zeroes the motors: `GpiozeroMotors` starts at zero, `close()`
and leaving its `with` block (normally or by an exception) zero it, and `stop_all_motors` does it from another
process after a crash. Both leave the twelve pins outputs driven low (inputs would let the L298's inputs float), and
both remove a deadman script a killed owner left guarding these pins (drivers.pigpiod.deadman): it would stop the
next owner's motors.

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

from drivers.pigpiod.client import CommandPipe, PigpiodUnavailableError, probe, stop_pigpio_client
from drivers.pigpiod.deadman import remove_deadmen
from drivers.pigpiod.protocol import Cmd
from drivers.settings import MotorPinsLike, MotorSettings, PigpiodAddress, in_wheel_order

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


def wheel_pins(motors: MotorSettings) -> list[MotorPinsLike]:
    """The motors' pins in wheel order."""
    return in_wheel_order(motors.wheels)


def enable_and_direction_pins(motors: MotorSettings) -> tuple[list[int], list[int]]:
    """The four enable pins, then the eight direction pins, in wheel order."""
    pins = wheel_pins(motors)
    return [p.enable for p in pins], [gpio for p in pins for gpio in (p.in1, p.in2)]


def command_duty(duty: float, sign: int, limit: float) -> float:
    """The duty to apply: wheel sign applied, clamped to [-limit, limit]; not-a-number stops the wheel."""
    if not math.isfinite(duty):
        return 0.0
    return max(-limit, min(limit, duty * sign))


class _Channel:
    """One L298 channel: its gpiozero devices, and what it last sent so an unchanged duty costs no round trip."""

    def __init__(self, pins: MotorPinsLike, frequency_hz: int, factory: Any) -> None:
        from gpiozero import DigitalOutputDevice, PWMOutputDevice  # noqa: PLC0415 - gpiozero is slow to import

        self.devices: list[Any] = []
        self.enable = self._add(PWMOutputDevice(pins.enable, frequency=frequency_hz, pin_factory=factory))
        self.in1 = self._add(DigitalOutputDevice(pins.in1, initial_value=False, pin_factory=factory))
        self.in2 = self._add(DigitalOutputDevice(pins.in2, initial_value=False, pin_factory=factory))
        self.enable_gpio = pins.enable
        self.in1_bit, self.in2_bit = 1 << pins.in1, 1 << pins.in2
        self.pwm_range = int(factory.connection.get_PWM_range(pins.enable))
        self.direction = 0
        self.counts = 0  # enable duty in PWM range units, as last written

    def _add(self, device: Any) -> Any:
        self.devices.append(device)
        return device

    def target(self, duty: float) -> tuple[int, int]:
        """Direction (-1, 0, 1) and enable duty in PWM units for a duty in [-1, 1] (truncated, as gpiozero does)."""
        return (duty > 0) - (duty < 0), int(abs(duty) * self.pwm_range)


class GpiozeroMotors:
    """The four L298 channels on gpiozero's PiGPIOFactory; a context manager that zeroes the motors on exit.

    gpiozero creates and owns the pins (modes, PWM frequency and range, release on close): it is good at that, and
    it runs once, off the event loop. The hot path leaves it: one `set_duties` per control period goes through a
    `CommandPipe`, every command of a period in one write that never waits for pigpiod's answers. gpiozero's PWM
    setter makes three blocking round trips per change (read the range, read the duty, write), each a sleep of the
    event loop's thread, and a stalled pigpiod would stall the loop with it; here the range is read once, the eight
    direction pins change in two bank writes and each enable in one, all in order on one socket (the bridge rule
    holds), and the answers are read when they have arrived. A pigpiod that refuses, stalls or goes away makes
    `set_duties` raise (the daemon then reconnects); `zero` and `close` write through the pipe too, and fall back
    to gpiozero's connection only when the pipe is broken.
    """

    def __init__(self, motors: MotorSettings, pigpiod: PigpiodAddress) -> None:
        # pigpio's client prints a banner and hands back a dead connection when pigpiod is absent: ask first.
        probe(pigpiod.host, pigpiod.port, pigpiod.connect_timeout_s)
        from gpiozero.pins.pigpio import PiGPIOFactory  # noqa: PLC0415 - gpiozero is slow to import

        self._motors = motors
        self._factory: Any = PiGPIOFactory(host=pigpiod.host, port=pigpiod.port)
        self._pi: Any = self._factory.connection
        self._channels: list[_Channel] = []
        self._pipe: CommandPipe | None = None
        self._flush_timeout_s = pigpiod.connect_timeout_s
        enables, directions = enable_and_direction_pins(motors)
        try:
            remove_deadmen(self._pi, [*enables, *directions])  # before it can stop these motors
            for pins in wheel_pins(motors):
                self._channels.append(_Channel(pins, motors.pwm_frequency_hz, self._factory))
            self._pipe = CommandPipe(pigpiod.host, pigpiod.port, pigpiod.connect_timeout_s)
        except BaseException:
            self.close()
            raise
        self._signs = [pins.sign for pins in wheel_pins(motors)]

    def set_duties(self, duties: Duties) -> None:
        """Apply one duty per wheel in [-1, 1]; a failure zeroes every motor before it propagates."""
        try:
            limit = self._motors.duty_limit
            targets = [
                channel.target(command_duty(duty, sign, limit))
                for channel, duty, sign in zip(self._channels, duties, self._signs, strict=True)
            ]
            self._write(targets)
        except BaseException:
            self.zero()
            raise

    def _write(self, targets: list[tuple[int, int]]) -> None:
        commands: list[tuple[int, int, int]] = []
        low = high = 0
        for channel, (direction, _) in zip(self._channels, targets, strict=True):
            if direction == channel.direction:
                continue
            if channel.counts:
                # Enable off before the inputs change: never drive the bridge through a half-switched state.
                commands.append((Cmd.PWM, channel.enable_gpio, 0))
                channel.counts = 0
            low |= channel.in1_bit | channel.in2_bit
            high |= channel.in1_bit if direction > 0 else channel.in2_bit if direction < 0 else 0
            channel.direction = direction
        if low:
            commands.append((Cmd.BC1, low, 0))
        if high:
            commands.append((Cmd.BS1, high, 0))
        for channel, (_, counts) in zip(self._channels, targets, strict=True):
            if counts != channel.counts:
                commands.append((Cmd.PWM, channel.enable_gpio, counts))
                channel.counts = counts
        if commands:
            self._send(commands)

    def _send(self, commands: list[tuple[int, int, int]]) -> None:
        if self._pipe is None:
            raise ConnectionError("the motor outputs are closed")
        self._pipe.send(commands)

    def zero(self) -> None:
        """Stop every motor (coast): enable at 0, both inputs low; every pin is written, whatever was cached."""
        directions = 0
        for channel in self._channels:
            channel.counts, channel.direction = 0, 0
            directions |= channel.in1_bit | channel.in2_bit
        stop = [(Cmd.PWM, channel.enable_gpio, 0) for channel in self._channels]  # enables first: the bridge rule
        try:
            self._send([*stop, (Cmd.BC1, directions, 0)])
        except Exception:  # noqa: BLE001 - the pipe is broken: try gpiozero's own connection
            self._zero_through_gpiozero()

    def _zero_through_gpiozero(self) -> None:
        for channel in self._channels:
            with contextlib.suppress(Exception):  # zero the others even if one pin fails
                channel.enable.value = 0.0
                channel.counts = 0
                channel.in1.off()
                channel.in2.off()
                channel.direction = 0

    def close(self) -> None:
        """Zero the motors, leave every motor pin an output driven low, and disconnect."""
        self.zero()
        enables, directions = enable_and_direction_pins(self._motors)
        pins = [*enables, *directions]  # enables first: the bridge rule
        pipe, self._pipe = self._pipe, None
        written = False
        if pipe is not None:
            with contextlib.suppress(Exception):  # pigpiod gone or stalled: gpiozero's connection is tried below
                pipe.send([(Cmd.WRITE, gpio, 0) for gpio in pins])
                written = pipe.flush(self._flush_timeout_s)  # carried out before gpiozero lets go of the pins
            pipe.close()
        if not written:
            for gpio in pins:
                with contextlib.suppress(Exception):  # pigpiod gone: nothing is driven any more
                    self._pi.write(gpio, 0)
        # gpiozero's close returns its pins to inputs, which would leave the L298's inputs floating; on a stopped
        # connection it writes nothing, so stop it first and let gpiozero only forget its devices.
        with contextlib.suppress(Exception):
            stop_pigpio_client(self._pi, self._flush_timeout_s)
        # Each release on its own: with pigpiod gone every one fails, and one failure must not leave the rest
        # (and the factory) for gpiozero's finalisers to retry and report at exit.
        for channel in self._channels:
            for device in channel.devices:
                try:
                    device.close()
                except Exception:  # noqa: BLE001 - pigpiod is gone: the pin cannot be released, only forgotten
                    # gpiozero would retry the close in its finaliser and print a traceback per pin at exit;
                    # a device with no pin is closed as far as gpiozero is concerned.
                    device._pin = None
        self._channels = []
        if self._factory is not None:
            with contextlib.suppress(Exception):
                self._factory.close()
            self._factory = None

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None
    ) -> None:
        self.close()


def stop_all_motors(motors: MotorSettings, pigpiod: PigpiodAddress) -> None:
    """Drive every motor pin low through pigpiod, without the daemon (blocking; for systemd's ExecStopPost).

    This uses pigpio directly, not gpiozero: gpiozero returns its pins to inputs when it closes, which would leave
    the L298 inputs floating after this process exits; pigpio's write leaves them outputs driven low. A deadman
    script left by the dead daemon is removed afterwards (it would only have zeroed them too).
    """
    import pigpio  # noqa: PLC0415 - only this path needs the raw client

    probe(pigpiod.host, pigpiod.port, pigpiod.connect_timeout_s)
    pi: Any = pigpio.pi(pigpiod.host, pigpiod.port, show_errors=False)
    if not pi.connected:
        raise PigpiodUnavailableError(pigpiod.host, pigpiod.port, "pigpio client could not connect")
    try:
        enables, directions = enable_and_direction_pins(motors)
        for gpio in [*enables, *directions]:  # enables first: the bridge rule
            pi.write(gpio, 0)  # also stops PWM on the pin
        remove_deadmen(pi, [*enables, *directions])
    finally:
        stop_pigpio_client(pi, pigpiod.connect_timeout_s)


@contextlib.contextmanager
def termination_as_exit() -> Iterator[None]:
    """Within this block SIGTERM, SIGHUP and SIGQUIT raise SystemExit, so `with` blocks and `finally` clauses run.

    For blocking programs on the main thread (the daemon has its own asyncio signal handlers).
    """

    def exit_on_signal(signum: int, _frame: FrameType | None) -> None:
        raise SystemExit(128 + signum)

    previous = {sig: signal.signal(sig, exit_on_signal) for sig in (signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
