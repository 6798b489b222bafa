"""`robotd stop-motors`, `robotd spin-wheels` and `robotd vpigpiod`: the wheels' I/O without the daemon."""

from __future__ import annotations

import argparse
import asyncio
import os
import signal
import sys
import time

from drivers.pigpiod.client import PigpiodUnavailableError
from robotd.config.model import RobotdConfig, load
from robotd.config.motorpins import StopTargets, read_stop_targets


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add the wheel I/O sub-commands."""
    stop = subparsers.add_parser(
        "stop-motors",
        help="stop every motor on the configured GPIO back-end: pins low through pigpiod, or the RP1's PWM at 0 on a"
        " Pi 5 (systemd ExecStopPost; no daemon needed)",
    )
    stop.add_argument(
        "--config",
        metavar="PATH",
        help="configuration with the motor pins, pigpiod and gpio sections (default: built-in); any field it cannot"
        " read is replaced by its built-in value, with a line on stderr",
    )
    stop.set_defaults(handler=stop_motors)

    spin = subparsers.add_parser(
        "spin-wheels", help="run the motors at fixed duties to check wiring and signs; zeroed on exit or SIGTERM"
    )
    spin.add_argument(
        "--config", metavar="PATH", help="configuration with the motor pins and pigpiod (default: built-in)"
    )
    spin.add_argument(
        "--duty", nargs=4, type=float, required=True, metavar=("FL", "FR", "RL", "RR"), help="duties in [-1, 1]"
    )
    spin.add_argument("--seconds", type=float, default=2.0, help="how long to run (default 2)")
    spin.set_defaults(handler=spin_wheels)

    sim = subparsers.add_parser("vpigpiod", help="run the virtual pigpiod alone (pigpio's socket protocol)")
    sim.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    sim.add_argument("--port", type=int, default=8888, help="TCP port (default 8888, pigpiod's)")
    sim.set_defaults(handler=vpigpiod)


def _config(path: str | None) -> RobotdConfig:
    return load(path) if path else RobotdConfig()


def stop_motors(args: argparse.Namespace) -> int:
    """Zero every motor on the configured back-end with the pins it can read (defaults for the rest).

    Exit 69 when the back-end is unreachable (pigpiod, or the RP1's PWM chip), 1 when a PWM channel could not be
    stopped, else 0.
    """
    from robotd.config.gpio import resolve_backend  # noqa: PLC0415 - keep `robotd --help` fast

    targets = read_stop_targets(args.config)  # never refuses: a broken file still leaves the pins it can read
    for fallback in targets.fallbacks:
        print(f"robotd stop-motors: {fallback}", file=sys.stderr)
    if resolve_backend(targets.gpio) == "gpiod":
        return _stop_gpiod_motors(targets)
    from drivers.wheels.motors import stop_all_motors  # noqa: PLC0415

    try:
        stop_all_motors(targets.motors, targets.pigpiod)
    except PigpiodUnavailableError as error:
        print(f"robotd stop-motors: {error}", file=sys.stderr)
        return os.EX_UNAVAILABLE
    print(f"robotd stop-motors: all motor pins low on {targets.pigpiod.host}:{targets.pigpiod.port}")
    return 0


def _stop_gpiod_motors(targets: StopTargets) -> int:
    """The gpiod back-end's stop: every RP1 PWM channel of the enable pins at 0, the direction pins low if free."""
    from drivers.gpiod.lines import GpioUnavailableError  # noqa: PLC0415
    from drivers.gpiod.motors import stop_gpiod_motors  # noqa: PLC0415
    from drivers.wheels.motors import enable_and_direction_pins  # noqa: PLC0415

    gpio = targets.gpio
    enables, directions = enable_and_direction_pins(targets.motors)
    try:
        report = stop_gpiod_motors(
            enables,
            directions,
            pwm_root=gpio.pwm_class_dir,
            pwm_device=gpio.pwm_device,
            gpio_chip=gpio.gpio_chip or None,
        )
    except (GpioUnavailableError, ValueError) as error:  # ValueError: an enable pin without RP1 PWM
        print(f"robotd stop-motors: {error}", file=sys.stderr)
        return os.EX_UNAVAILABLE
    for problem in report.pwm_problems:
        print(f"robotd stop-motors: could not stop {problem}", file=sys.stderr)
    if report.direction_note is not None:
        print(f"robotd stop-motors: {report.direction_note}", file=sys.stderr)
    if report.pwm_problems:
        return 1
    print(f"robotd stop-motors: every RP1 PWM channel of GPIO {', '.join(map(str, enables))} stopped")
    return 0


def spin_wheels(args: argparse.Namespace) -> int:
    """Hold the given duties for a while; the motors are zeroed however the program ends."""
    from drivers.wheels.motors import GpiozeroMotors, termination_as_exit  # noqa: PLC0415

    config = _config(args.config)
    duties = (args.duty[0], args.duty[1], args.duty[2], args.duty[3])
    try:
        with termination_as_exit(), GpiozeroMotors(config.motors, config.pigpiod) as motors:
            motors.set_duties(duties)
            print(f"robotd spin-wheels: duties {duties} for {args.seconds} s", flush=True)
            time.sleep(args.seconds)
    except PigpiodUnavailableError as error:
        print(f"robotd spin-wheels: {error}", file=sys.stderr)
        return os.EX_UNAVAILABLE
    return 0


def vpigpiod(args: argparse.Namespace) -> int:
    """Serve the virtual pigpiod until SIGINT or SIGTERM."""
    from drivers.virtual.pigpiod import VirtualPigpiod  # noqa: PLC0415

    async def serve() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        async with VirtualPigpiod(args.host, args.port) as server:
            print(f"robotd vpigpiod: virtual pigpiod (Pi 4B) on {args.host}:{server.port}", flush=True)
            await stop.wait()

    try:
        asyncio.run(serve())
    except OSError as error:
        print(f"robotd vpigpiod: cannot listen on {args.host}:{args.port}: {error}", file=sys.stderr)
        return os.EX_UNAVAILABLE
    return 0
