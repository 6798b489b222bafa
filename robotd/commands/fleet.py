"""`robotd fleet`: every robot on the broker in a live table; `robotd fleet stop` and `robotd fleet release`."""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from robotd.fleet.operator import BrokerAddress
    from robotd.fleet.secrets import Credentials

ENV_BROKER = "ROBOTD_FLEET_BROKER"
ENV_CREDENTIALS = "ROBOTD_FLEET_CREDENTIALS"
ENV_KEY = "ROBOTD_FLEET_KEY"


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `robotd fleet` with its `stop` and `release` actions."""
    fleet = subparsers.add_parser(
        "fleet", help="watch every robot on the MQTT broker (live table); stop or release them (signed, retained)"
    )
    _broker_options(fleet)
    fleet.add_argument("--for", dest="duration", type=float, default=None, metavar="S", help="stop watching after S s")
    fleet.add_argument("--once", action="store_true", help="print the table once (after 2 s of listening) and exit")
    fleet.set_defaults(handler=run_watch)
    actions = fleet.add_subparsers(dest="action", metavar="ACTION")
    for name, what in (("stop", "stop and hold"), ("release", "release")):
        order = actions.add_parser(name, help=f"{what} one robot, or every robot with --all (retained until changed)")
        _broker_options(order, suppress=True)  # given before the action or after it
        target = order.add_mutually_exclusive_group(required=True)
        target.add_argument("robot", nargs="?", help="the robot id")
        target.add_argument("--all", action="store_true", help="the whole fleet (robotd/fleet/stop)")
        order.add_argument("--key", default=os.environ.get(ENV_KEY), help=f"the fleet key file (default ${ENV_KEY})")
        order.set_defaults(handler=run_order, order=name)
    view = actions.add_parser(
        "view", help="serve every robot on the broker to Foxglove (WebSocket; poses, ellipses, trails, frames, status)"
    )
    _broker_options(view, suppress=True)
    view.add_argument("--host", default="127.0.0.1", help="address to serve on (default loopback: 127.0.0.1)")
    view.add_argument("--port", type=int, default=8765, help="WebSocket port (default 8765, Foxglove's; 0: a free one)")
    view.add_argument("--trail", type=float, default=120.0, metavar="S", help="trail length in seconds (default 120)")
    view.add_argument("--for", dest="duration", type=float, default=argparse.SUPPRESS, metavar="S", help="for S s")
    view.set_defaults(handler=run_view)


def _broker_options(parser: argparse.ArgumentParser, *, suppress: bool = False) -> None:
    # an action's own options default to nothing, so that they do not overwrite the same options given before it
    def default(value: str | None) -> str | None:
        return argparse.SUPPRESS if suppress else value

    parser.add_argument(
        "--broker",
        default=default(os.environ.get(ENV_BROKER, "mqtt://127.0.0.1:1883")),
        help=f"mqtt://HOST:PORT or mqtts://HOST:PORT (default ${ENV_BROKER}, else mqtt://127.0.0.1:1883)",
    )
    parser.add_argument(
        "--credentials",
        default=default(os.environ.get(ENV_CREDENTIALS)),
        metavar="FILE",
        help=f"`username:password` file (default ${ENV_CREDENTIALS}; none: anonymous)",
    )
    parser.add_argument(
        "--ca-file", default=default(None), help="CA certificate of an mqtts:// broker (default: the system's)"
    )


def _connection(args: argparse.Namespace) -> tuple[BrokerAddress, Credentials | None] | None:
    from robotd.fleet.operator import BrokerAddress  # noqa: PLC0415 - aiomqtt only for this command
    from robotd.fleet.secrets import load_credentials  # noqa: PLC0415

    try:
        address = BrokerAddress.parse(args.broker)
    except ValueError as error:
        print(f"robotd fleet: --broker: {error}", file=sys.stderr)
        return None
    credentials = load_credentials(args.credentials, "--credentials") if args.credentials else None
    return address, credentials


def run_watch(args: argparse.Namespace) -> int:
    """The live table until Ctrl-C (or --for S, or --once)."""
    import aiomqtt  # noqa: PLC0415

    from robotd.fleet.operator import watch  # noqa: PLC0415

    connection = _connection(args)
    if connection is None:
        return 2
    address, credentials = connection
    once = args.once
    duration = 2.0 if once else args.duration
    refresh = 2.0 if once else 0.5
    try:
        asyncio.run(
            watch(address, credentials, duration_s=duration, refresh_s=refresh,
                  in_place=sys.stdout.isatty() and not once, ca_file=args.ca_file)
        )  # fmt: skip
    except aiomqtt.MqttError as error:
        print(f"robotd fleet: broker {args.broker}: {error}", file=sys.stderr)
        return 1
    return 0


def run_order(args: argparse.Namespace) -> int:
    """Publish a signed stop or release; says which topics it went to."""
    import aiomqtt  # noqa: PLC0415

    from robotd.fleet.operator import read_key, send_orders  # noqa: PLC0415
    from robotd.fleet.orders import Action  # noqa: PLC0415

    if not args.key:
        print(f"robotd fleet {args.order}: --key FILE (or ${ENV_KEY}) is required: orders are signed", file=sys.stderr)
        return 2
    connection = _connection(args)
    if connection is None:
        return 2
    address, credentials = connection
    key = read_key(Path(args.key))
    action = Action(args.order)
    target = None if args.all else args.robot
    try:
        sent = asyncio.run(send_orders(address, credentials, key, action, target=target, ca_file=args.ca_file))
    except aiomqtt.MqttError as error:
        print(f"robotd fleet {args.order}: broker {args.broker}: {error}", file=sys.stderr)
        return 1
    print(f"robotd fleet: {action.value} published (retained) to {', '.join(sent)}")
    return 0


def run_view(args: argparse.Namespace) -> int:
    """Serve the fleet to Foxglove until Ctrl-C (or --for S); says where to connect."""
    import aiomqtt  # noqa: PLC0415

    from robotd.fleet.view import ViewServer, serve_fleet_view  # noqa: PLC0415

    connection = _connection(args)
    if connection is None:
        return 2
    address, credentials = connection

    def ready(port: int) -> None:
        print(f"robotd fleet view: {address} served on ws://{args.host}:{port} (Foxglove: Open connection)", flush=True)

    server = ViewServer(args.host, args.port, args.trail)
    try:
        asyncio.run(serve_fleet_view(address, credentials, server, duration_s=args.duration, ca_file=args.ca_file,
                                     on_ready=ready))  # fmt: skip
    except aiomqtt.MqttError as error:
        print(f"robotd fleet view: broker {args.broker}: {error}", file=sys.stderr)
        return 1
    except RuntimeError as error:  # the SDK's reason the port cannot be served
        print(f"robotd fleet view: cannot serve on {args.host}:{args.port}: {error}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 0
    return 0
