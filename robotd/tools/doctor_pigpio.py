"""The doctor's pigpio back-end: pigpiod through the real `pigpio` client, encoders through robotd's own reader.

The wheel drive writes the L298 pins with raw pigpio calls, not gpiozero: gpiozero turns its pins back into inputs
when it closes, which would leave a running daemon's cached motor outputs silently disconnected; this drive ends as
`robotd stop-motors` does, every motor pin an output driven low.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Callable, Sequence
from typing import Any

from drivers.pigpiod.client import PigpiodUnavailableError, probe, stop_pigpio_client
from drivers.pigpiod.protocol import Mode
from drivers.wheels.encoders import PigpioEncoders
from drivers.wheels.motors import command_duty, wheel_pins
from robotd.config.model import PigpiodConfig, RobotdConfig
from robotd.tools.gpio_backend import BackendUnavailableError, Counts, GpioBackend

START_HINT = (
    "start it: sudo systemctl enable --now pigpiod (a Pi 5 cannot run pigpio: robotd needs its gpiod back-end there);"
    " with the virtual robot, start robotd vhw --config CONFIG"
)


def _connect(pigpiod: PigpiodConfig) -> Any:
    """A connected pigpio client, or BackendUnavailableError (asks first: pigpio hands back a dead client)."""
    import pigpio  # noqa: PLC0415 - only the doctor's hardware paths need the client

    where = f"{pigpiod.host}:{pigpiod.port}"
    try:
        probe(pigpiod.host, pigpiod.port, pigpiod.connect_timeout_s)
    except PigpiodUnavailableError as error:
        raise BackendUnavailableError(f"pigpiod does not answer at {where} ({error.__cause__})", START_HINT) from None
    pi = pigpio.pi(pigpiod.host, pigpiod.port, show_errors=False)
    if not pi.connected:
        raise BackendUnavailableError(f"something at {where} accepts connections but is not pigpiod", START_HINT)
    return pi


def reach(config: RobotdConfig) -> str:
    """pigpiod's version and the board's hardware revision, as pigpiod reports them."""
    pi = _connect(config.pigpiod)
    try:
        version = pi.get_pigpio_version()
        revision = pi.get_hardware_revision()
    finally:
        stop_pigpio_client(pi)
    return f"pigpiod {version} at {config.pigpiod.host}:{config.pigpiod.port}, hardware revision {revision:x}"


def pin_modes(config: RobotdConfig, pins: Sequence[int]) -> dict[int, str]:
    """Each pin's mode as pigpiod reads it from the GPIO registers."""
    pi = _connect(config.pigpiod)
    try:
        return {pin: Mode(pi.get_mode(pin)).name.lower() for pin in pins}
    finally:
        stop_pigpio_client(pi)


class PigpioWheelDrive:
    """The four L298 channels, one wheel at a time, through raw pigpio calls (see the module docstring)."""

    def __init__(self, config: RobotdConfig) -> None:
        self._pi = _connect(config.pigpiod)
        self._pins = wheel_pins(config.motors)
        self._limit = config.motors.duty_limit
        try:
            self.stop()
            for pins in self._pins:
                self._pi.set_PWM_frequency(pins.enable, config.motors.pwm_frequency_hz)
            self._ranges = [int(self._pi.get_PWM_range(pins.enable)) for pins in self._pins]
            self.stop()
        except BaseException:
            self.close()
            raise

    def drive(self, wheel: int, duty: float) -> None:
        """One wheel at a forward duty (its motor sign and the duty limit applied); the others off."""
        self.stop()  # every enable low before any direction input changes (the bridge rule)
        pins = self._pins[wheel]
        applied = command_duty(duty, pins.sign, self._limit)
        self._pi.write(pins.in1, int(applied > 0))
        self._pi.write(pins.in2, int(applied < 0))
        self._pi.set_PWM_dutycycle(pins.enable, int(abs(applied) * self._ranges[wheel]))

    def stop(self) -> None:
        """Every motor pin an output driven low (enable first)."""
        for pins in self._pins:
            for gpio in (pins.enable, pins.in1, pins.in2):
                self._pi.write(gpio, 0)

    def close(self) -> None:
        """Stop, then disconnect."""
        try:
            self.stop()
        finally:
            stop_pigpio_client(self._pi)


@contextlib.asynccontextmanager
async def open_counts(config: RobotdConfig) -> AsyncIterator[Callable[[], Counts]]:
    """robotd's own encoder reader on pigpiod's notification stream, running while the block runs."""
    encoders = PigpioEncoders(config.encoders, config.pigpiod)
    reader = asyncio.create_task(encoders.run(lambda _ticks: None), name="doctor-encoders")
    try:
        try:
            async with asyncio.timeout(4 * config.pigpiod.connect_timeout_s):
                while not encoders.connected:
                    if reader.done():
                        reader.result()  # the reason it could not connect
                    await asyncio.sleep(0.01)
        except (PigpiodUnavailableError, TimeoutError) as error:
            raise BackendUnavailableError(f"no encoder stream from pigpiod ({error})", START_HINT) from None
        yield lambda: encoders.snapshot().ticks
    finally:
        reader.cancel()
        with contextlib.suppress(asyncio.CancelledError, PigpiodUnavailableError, OSError):
            await reader


PIGPIO = GpioBackend(
    name="pigpio",
    reach=reach,
    pin_modes=pin_modes,
    open_drive=PigpioWheelDrive,
    open_counts=open_counts,
)
