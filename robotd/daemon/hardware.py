"""The daemon's wheels built from the configuration in one place: encoders, motors and their deadman, per back-end.

`build_hardware` picks the back-end by name (`gpio.backend`, `auto` resolved by the board: robotd.config.gpio) and
builds what the daemon needs from it; nothing here touches a pin (motors are connected later, by the factory, off the
event loop). The stop paths differ by back-end:
- pigpio: pigpiod keeps driving after its client dies, so a deadman script inside pigpiod (drivers.pigpiod.deadman)
  stops the motors when the control loop stops bumping it (killed, stopped or hung), if `motors.deadman_script`.
- gpiod: sysfs PWM keeps running after its process dies, so a watchdog process started with the motors
  (drivers.gpiod.watchdog) stops the PWM when robotd dies, if `gpio.pwm_watchdog`; with `motors.deadman_script`
  too it is also the deadman (drivers.gpiod.deadman): bumped by the control loop like pigpio's script, it zeroes
  the PWM when robotd is stopped or hung.
Both leave `robotd stop-motors` for systemd's ExecStopPost.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path

from drivers.gpiod.deadman import GpiodDeadman
from drivers.gpiod.encoders import GpiodEncoders
from drivers.gpiod.lines import (
    EventLineSettings,
    EventLinesOpener,
    GpioUnavailableError,
    LineHoldersReader,
    OutputLinesOpener,
    open_event_lines,
    open_output_lines,
    read_line_holders,
)
from drivers.gpiod.motors import GpiodMotors
from drivers.gpiod.pwm import SYSFS, Attributes, find_pwm_chip
from drivers.pigpiod.deadman import Deadman, PigpioDeadman
from drivers.wheels.encoders import EncoderSource, PigpioEncoders, wiring
from drivers.wheels.motors import GpiozeroMotors, MotorOutputs, enable_and_direction_pins, wheel_pins
from robotd.config.gpio import Backend, resolve_backend
from robotd.config.model import RobotdConfig
from robotd.daemon.deadman_keeper import DeadmanFactory
from robotd.daemon.pacer import rest_period_s


@dataclass(frozen=True, slots=True)
class GpiodIo:
    """Where the gpiod back-end's line requests and PWM writes go: the kernel's by default, stand-ins in tests."""

    open_event_lines: EventLinesOpener = open_event_lines
    open_output_lines: OutputLinesOpener = open_output_lines
    pwm_attributes: Attributes = SYSFS
    read_line_holders: LineHoldersReader = read_line_holders


@dataclass(frozen=True, slots=True)
class Hardware:
    """The back-end chosen and what the daemon runs on it."""

    backend: Backend
    encoders: EncoderSource
    motors_factory: Callable[[], MotorOutputs]
    """Connects the motors (blocking: the daemon calls it in a thread); zeroed from the start."""
    deadman_factory: DeadmanFactory | None
    """Installs a deadman for the motors just connected; None when the back-end or the configuration has none."""


def build_hardware(
    config: RobotdConfig,
    clock: Callable[[], float],
    *,
    gpiod_io: GpiodIo | None = None,
    root: Path = Path("/"),
) -> Hardware:
    """The wheels of the back-end `config` names, on the machine whose root directory is `root`."""
    backend = resolve_backend(config.gpio, root)
    if backend == "gpiod":
        return _gpiod(config, clock, gpiod_io or GpiodIo())
    return _pigpio(config, clock)


def deadman_timeout_s(config: RobotdConfig) -> float:
    """How long a deadman waits for a heartbeat, either back-end: `teleop.deadman_timeout_s`, at least two periods
    (a timeout the control loop's own jitter could reach would trip while robotd runs)."""
    return max(config.teleop.deadman_timeout_s, 2.0 / config.control.rate_hz)


def _pigpio(config: RobotdConfig, clock: Callable[[], float]) -> Hardware:
    pigpiod = config.pigpiod

    def install_deadman() -> Awaitable[Deadman]:
        period = 1.0 / config.control.rate_hz
        enables, directions = enable_and_direction_pins(config.motors)
        timeout = deadman_timeout_s(config)
        return PigpioDeadman.install(
            pigpiod.host,
            pigpiod.port,
            pigpiod.connect_timeout_s,
            enables,
            directions,
            timeout_s=timeout,
            period_s=period,
            heartbeat_s=rest_period_s(period, config.teleop.deadman_timeout_s),
        )

    return Hardware(
        "pigpio",
        PigpioEncoders(config.encoders, pigpiod, clock),
        lambda: GpiozeroMotors(config.motors, pigpiod),
        install_deadman if config.motors.deadman_script else None,
    )


def gpiod_motors(config: RobotdConfig, io: GpiodIo, *, heartbeat_timeout_s: float | None = None) -> GpiodMotors:
    """The gpiod back-end's four L298 channels as the configuration describes them (the daemon's and the doctor's)."""
    gpio, motors = config.gpio, config.motors
    return GpiodMotors(
        wheel_pins(motors),
        frequency_hz=motors.pwm_frequency_hz,
        duty_limit=motors.duty_limit,
        pwm_chip=find_pwm_chip(gpio.pwm_device, gpio.pwm_class_dir),
        attributes=io.pwm_attributes,
        open_outputs=io.open_output_lines,
        gpio_chip=gpio.gpio_chip or None,
        watchdog=gpio.pwm_watchdog,
        heartbeat_timeout_s=heartbeat_timeout_s,
    )


def _gpiod(config: RobotdConfig, clock: Callable[[], float], io: GpiodIo) -> Hardware:
    gpio, encoders, motors = config.gpio, config.encoders, config.motors
    chip = gpio.gpio_chip or None
    settings = EventLineSettings(chip=chip, pull=encoders.pull, event_buffer_size=gpio.event_buffer_size)
    source = GpiodEncoders(
        wiring(encoders),
        encoders.counts_per_rev,
        decoding=encoders.decoding,
        publish_rate_hz=encoders.publish_rate_hz,
        settings=settings,
        open_lines=io.open_event_lines,
        clock=clock,
    )

    heartbeat = gpio.pwm_watchdog and motors.deadman_script
    connected: list[GpiodMotors] = []  # the motors connected last: their watchdog is the deadman installed next

    def connect_motors() -> GpiodMotors:
        connected.clear()
        connected.append(gpiod_motors(config, io, heartbeat_timeout_s=deadman_timeout_s(config) if heartbeat else None))
        return connected[0]

    async def install_deadman() -> Deadman:
        watchdog = connected[0].watchdog if connected else None
        if watchdog is None:
            raise GpioUnavailableError("no PWM watchdog runs for the motors: connect them before the deadman")
        return GpiodDeadman(watchdog)

    return Hardware("gpiod", source, connect_motors, install_deadman if heartbeat else None)
