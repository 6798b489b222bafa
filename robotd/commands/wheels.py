"""`robotd stop-motors`, `robotd spin-wheels` and `robotd vpigpiod`: the wheels' I/O without the daemon."""

from __future__ import annotations

import argparse
import asyncio
import signal
import sys
import time

from drivers.pigpiod.client import PigpiodUnavailableError
from robotd.config.model import RobotdConfig, load
from robotd.config.motorpins import read_stop_targets

EX_UNAVAILABLE = 69


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add the wheel I/O sub-commands."""
    stop = subparsers.add_parser(
        "stop-motors", help="drive every motor pin low through pigpiod (systemd ExecStopPost; no daemon needed)"
    )
    stop.add_argument(
        "--config",
        metavar="PATH",
        help="configuration with the motor pins and pigpiod (default: built-in); any field it cannot read is"
        " replaced by its built-in value, with a line on stderr",
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
    """Zero every motor through pigpiod with the pins it can read (defaults for the rest); 69: pigpiod unreachable."""
    from drivers.wheels.motors import stop_all_motors  # noqa: PLC0415 - keep `robotd --help` fast

    targets = read_stop_targets(args.config)  # never refuses: a broken file still leaves the pins it can read
    for fallback in targets.fallbacks:
        print(f"robotd stop-motors: {fallback}", file=sys.stderr)
    try:
        stop_all_motors(targets.motors, targets.pigpiod)
    except PigpiodUnavailableError as error:
        print(f"robotd stop-motors: {error}", file=sys.stderr)
        return EX_UNAVAILABLE
    print(f"robotd stop-motors: all motor pins low on {targets.pigpiod.host}:{targets.pigpiod.port}")
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
        return EX_UNAVAILABLE
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
        return EX_UNAVAILABLE
    return 0
