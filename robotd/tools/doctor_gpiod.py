"""The doctor's gpiod back-end (a Raspberry Pi 5): libgpiod's line info and requests, the RP1's PWM through sysfs.

Built on the daemon's own drivers, with the same `GpiodIo` as robotd.daemon.hardware (the kernel's by default,
stand-ins in tests): reachable is the GPIO chip answering line info for every configured pin and the RP1's PWM chip
found by its device path; a pin is free when no other program holds its line; the spin drives `GpiodMotors` (zeroed
from the start, the bridge rule, its PWM watchdog stops the wheels if the doctor dies) while robotd's own
`GpiodEncoders` count. libgpiod cannot see a pin's function (I2C, SPI, UART): `pinctrl get` can, so that check says so.
A running robotd holds the lines: the spin then fails with the fix (stop robotd first).
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
from collections.abc import AsyncIterator, Callable, Sequence

from drivers.gpiod.encoders import GpiodEncoders
from drivers.gpiod.lines import EventLineSettings, GpioUnavailableError
from drivers.gpiod.pwm import RP1_PWM_CHANNELS, find_pwm_chip
from drivers.wheels.encoders import wiring
from robotd.config.model import RobotdConfig
from robotd.daemon.hardware import GpiodIo, gpiod_motors
from robotd.tools.doctor_pins import pins_in_use
from robotd.tools.gpio_backend import BackendUnavailableError, Counts, GpioBackend

INSTALL_HINT = (
    "on a Raspberry Pi 5: pip install 'robotd[pi5]' (gpiod >= 2.2), enable the RP1's PWM with the dtoverlay of the"
    " README's Pi section and reboot; elsewhere use gpio.backend: pigpio"
)
HELD_HINT = "stop robotd first (sudo systemctl stop robotd): it holds the motor and encoder lines while it runs"


def _unavailable(error: OSError) -> BackendUnavailableError:
    return BackendUnavailableError(str(error), HELD_HINT if error.errno == errno.EBUSY else INSTALL_HINT)


def gpiod_backend(io: GpiodIo | None = None) -> GpioBackend:
    """The doctor's view of the gpiod back-end, on the kernel's GPIO (or the stand-ins of `io`)."""
    io = io or GpiodIo()

    def reach(config: RobotdConfig) -> str:
        """The GPIO chip answering for every configured line, and the PWM chip with its path."""
        pins = [pin for _, pin in pins_in_use(config)]
        try:
            chip, _ = io.read_line_holders(pins, config.gpio.gpio_chip or None)
            pwm = find_pwm_chip(config.gpio.pwm_device, config.gpio.pwm_class_dir)
        except GpioUnavailableError as error:
            raise _unavailable(error) from None
        return f"GPIO chip {chip} answers for the {len(pins)} lines; PWM chip {pwm.name} ({config.gpio.pwm_device})"

    def pin_holders(config: RobotdConfig, pins: Sequence[int]) -> dict[int, str | None]:
        """Who holds each line now (None: free)."""
        try:
            return io.read_line_holders(pins, config.gpio.gpio_chip or None)[1]
        except GpioUnavailableError as error:
            raise _unavailable(error) from None

    def open_drive(config: RobotdConfig) -> GpiodWheelDrive:
        return GpiodWheelDrive(config, io)

    @contextlib.asynccontextmanager
    async def open_counts(config: RobotdConfig) -> AsyncIterator[Callable[[], Counts]]:
        """robotd's own encoder source on one line request, running while the block runs."""
        encoders_config = config.encoders
        encoders = GpiodEncoders(
            wiring(encoders_config),
            encoders_config.counts_per_rev,
            decoding=encoders_config.decoding,
            publish_rate_hz=encoders_config.publish_rate_hz,
            settings=EventLineSettings(
                chip=config.gpio.gpio_chip or None,
                pull=encoders_config.pull,
                event_buffer_size=config.gpio.event_buffer_size,
                consumer="robotd-doctor",
            ),
            open_lines=io.open_event_lines,
        )
        reader = asyncio.create_task(encoders.run(lambda _ticks: None), name="doctor-encoders")
        try:
            while not encoders.connected:
                if reader.done():
                    try:
                        reader.result()  # the reason it could not open the lines
                    except GpioUnavailableError as error:
                        raise _unavailable(error) from None
                await asyncio.sleep(0.01)
            yield lambda: encoders.snapshot().ticks
        finally:
            reader.cancel()
            with contextlib.suppress(asyncio.CancelledError, OSError):
                await reader

    return GpioBackend(
        name="gpiod",
        reach=reach,
        pin_modes=None,
        open_drive=open_drive,
        open_counts=open_counts,
        pwm_pins=frozenset(RP1_PWM_CHANNELS),
        pin_holders=pin_holders,
    )


class GpiodWheelDrive:
    """The four L298 channels, one wheel at a time, through the daemon's `GpiodMotors` (see the module docstring)."""

    def __init__(self, config: RobotdConfig, io: GpiodIo) -> None:
        try:
            self._motors = gpiod_motors(config, io)
        except (GpioUnavailableError, OSError) as error:
            raise _unavailable(error) from None

    def drive(self, wheel: int, duty: float) -> None:
        """One wheel at a forward duty (its motor sign and the duty limit applied); the others off."""
        duties = [0.0, 0.0, 0.0, 0.0]
        duties[wheel] = duty
        self._motors.set_duties((duties[0], duties[1], duties[2], duties[3]))

    def stop(self) -> None:
        """Every motor off: each enable at duty 0, then each direction input low."""
        self._motors.zero()

    def close(self) -> None:
        """Stop, disable and unexport the PWM, release the lines."""
        self._motors.close()
