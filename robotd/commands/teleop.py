"""`robotd teleop`: drive the robot over UDP from the keyboard, a fixed twist (`--send`) or the paper's square."""

from __future__ import annotations

import argparse
import sys

from robotd.config.model import RobotdConfig, TeleopConfig, load
from robotd.daemon.teleop import load_key
from robotd.kinematics import Twist
from robotd.tools.teleop_client import Leg, UdpLink, run_keyboard, run_plan, square_plan

SYNC_TIMEOUT_S = 2.0  # the daemon answers a hello within a round trip; this covers one that is still starting
CLOCK_WARNING_S = 1.0  # a clock offset worth a warning (a round trip on a network is milliseconds)


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `robotd teleop`."""
    parser = subparsers.add_parser("teleop", help="remote control: terminal keys, --send VX VY WZ, or --square SIDE")
    parser.add_argument("--config", metavar="PATH", help="read host, port and key file from this configuration")
    parser.add_argument("--host", help="robot address (default: the configured bind address, or 127.0.0.1)")
    parser.add_argument("--port", type=int, help="UDP port (default: the configured one, 47800)")
    parser.add_argument("--key-file", metavar="FILE", help="shared HMAC key (default: the configured teleop.key_file)")
    parser.add_argument(
        "--no-key", action="store_true", help="send unauthenticated (daemon needs allow_unauthenticated)"
    )
    parser.add_argument("--rate", type=float, default=20.0, metavar="HZ", help="commands per second (default 20)")
    plan = parser.add_mutually_exclusive_group()
    plan.add_argument("--send", nargs=3, type=float, metavar=("VX", "VY", "WZ"), help="send one twist (m/s, rad/s)")
    plan.add_argument("--square", type=float, metavar="SIDE", help="drive a square of SIDE metres open-loop")
    parser.add_argument("--for", dest="duration", type=float, default=1.0, metavar="SECONDS", help="with --send")
    parser.add_argument("--speed", type=float, default=0.2, metavar="MPS", help="with --square (default 0.2 m/s)")
    parser.add_argument("--loops", type=int, default=1, help="with --square: how many times round (default 1)")
    parser.add_argument("--pause", type=float, default=1.0, metavar="SECONDS", help="with --square: stop per corner")
    parser.set_defaults(handler=teleop)


def _key(args: argparse.Namespace, config: RobotdConfig | None) -> bytes | None:
    if args.no_key:
        return None
    if args.key_file:
        return load_key(args.key_file)
    if config is not None and config.teleop.key_file:
        return load_key(config.teleop.key_file)
    print("robotd teleop: no key (--key-file or teleop.key_file): sending unauthenticated", file=sys.stderr)
    return None


def teleop(args: argparse.Namespace) -> int:
    """Open a sender session and drive until the plan ends or the operator quits; always ends with a stop."""
    if args.rate <= 0 or args.duration < 0:
        print("robotd teleop: --rate must be > 0 and --for >= 0", file=sys.stderr)
        return 2
    config = load(args.config) if args.config else None
    bind = config.teleop.bind if config is not None else "127.0.0.1"
    host = args.host or ("127.0.0.1" if bind in ("0.0.0.0", "::", "") else bind)
    port = args.port or (config.teleop.port if config is not None else 47800)
    key = _key(args, config)
    link = UdpLink(host, port, key)
    if not link.sync(SYNC_TIMEOUT_S):
        print(
            f"robotd teleop: no answer from robotd at {host}:{port} (not running, or another key?): "
            "asking again while the plan runs; the robot does not move until it answers",
            file=sys.stderr,
        )
    elif abs(link.clock_offset_s) > CLOCK_WARNING_S:
        limit = config.teleop.max_clock_offset_s if config is not None else TeleopConfig().max_clock_offset_s
        print(
            f"robotd teleop: the robot's clock is {link.clock_offset_s:+.1f} s from this computer's; it refuses "
            f"commands beyond teleop.max_clock_offset_s ({limit:g} s): set both clocks (NTP)",
            file=sys.stderr,
        )
    try:
        if args.send is not None:
            run_plan(link, [Leg(Twist(*args.send), args.duration)], args.rate)
        elif args.square is not None:
            try:
                plan = square_plan(args.square, args.speed, args.loops, args.pause)
            except ValueError as error:
                print(f"robotd teleop: {error}", file=sys.stderr)
                return 2
            run_plan(link, plan, args.rate, report=lambda leg: print(f"{leg.twist} for {leg.duration_s:.2f} s"))
        else:
            if not sys.stdin.isatty():
                print("robotd teleop: interactive keys need a terminal; use --send or --square", file=sys.stderr)
                return 2
            run_keyboard(link, args.rate)
    finally:
        link.close()
    return 0
