"""`robotd pose`: print the daemon's pose stream for a person (one updating line), or raw with --json."""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Iterable
from typing import Any, TextIO

from robotd.config.model import load
from robotd.daemon import poseclient
from robotd.daemon.poseclient import PoseSocketMessage, unexpected_hello
from robotd.daemon.posesock import PROTOCOL, PROTOCOL_VERSION

DEFAULT_SOCKET = "/run/robotd/pose.sock"


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `robotd pose`."""
    parser = subparsers.add_parser("pose", help="print the pose stream of a running daemon")
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--config", metavar="PATH", help="read the socket path from this configuration")
    where.add_argument("--socket", metavar="PATH", help=f"pose socket (default {DEFAULT_SOCKET})")
    parser.add_argument("--json", action="store_true", help="print the raw JSON lines")
    parser.add_argument("--count", type=int, metavar="N", help="stop after N pose messages")
    parser.set_defaults(handler=pose)


def describe_pose(message: dict[str, Any]) -> str:
    """One line for a person: position, heading, speed, one-sigma uncertainty and sensor states."""
    cov = message.get("covariance") or [math.nan] * 9
    sigma_xy = math.sqrt(max(0.0, _number(cov[0]) + _number(cov[4])))
    sigma_theta = math.degrees(math.sqrt(max(0.0, _number(cov[8]))))
    age = message.get("fix_age_s")
    fix = f"{message.get('fix_state')} ({age:.2f} s ago)" if isinstance(age, int | float) else "none yet"
    return (
        f"x {_number(message.get('x')):+8.3f} m  y {_number(message.get('y')):+8.3f} m  "
        f"theta {math.degrees(_number(message.get('theta'))):+7.1f} deg  "
        f"v ({_number(message.get('vx')):+.2f}, {_number(message.get('vy')):+.2f}) m/s "
        f"{_number(message.get('wz')):+.2f} rad/s  "
        f"±{sigma_xy:.3f} m ±{sigma_theta:.1f} deg  fix {fix}  odometry {message.get('odometry_state')}"
    )


def _number(value: Any) -> float:
    return float(value) if isinstance(value, int | float) else math.nan


def show(received: Iterable[PoseSocketMessage], out: TextIO, raw: bool, count: int | None) -> int:
    """Print messages until they end or `count` poses were shown; returns the exit status (1 after an error message
    from the daemon or an unexpected protocol)."""
    poses = 0
    for item in received:
        message, kind = item.message, item.kind
        if message is None:
            print(f"robotd pose: skipping a line that is not a JSON object: {item.line[:60]!r}", file=sys.stderr)
            continue
        if raw:
            out.write(item.line)
            out.flush()
        elif kind == "hello":
            problem = unexpected_hello(message)
            if problem is not None:
                print(f"robotd pose: {problem}", file=sys.stderr)
                return 1
            print(f"connected: {PROTOCOL} v{PROTOCOL_VERSION}, {message.get('rate_hz')} Hz", file=out)
        elif kind == "pose":
            out.write(f"\r{describe_pose(message)}\x1b[K")
            out.flush()
        if kind == "error":  # the daemon says why it is closing the connection (e.g. too many clients)
            print(f"robotd pose: the daemon closed the connection: {message.get('error')}", file=sys.stderr)
            return 1
        if kind == "pose":
            poses += 1
            if count is not None and poses >= count:
                break
    if not raw:
        print(file=out)
    return 0


def pose(args: argparse.Namespace) -> int:
    """Connect to the pose socket and print what arrives."""
    path = load(args.config).pose_socket.path if args.config else (args.socket or DEFAULT_SOCKET)
    try:
        sock = poseclient.connect(path)
    except OSError as error:
        print(f"robotd pose: cannot connect to {path}: {error.strerror or error}", file=sys.stderr)
        return 1
    with sock:
        return show(poseclient.messages(sock), sys.stdout, args.json, args.count)
