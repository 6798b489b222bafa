"""`robotd ips decode FILE|-` and `robotd ips listen DEVICE`: Marvelmind streams as JSON lines, counters on stderr."""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import os
import sys
from collections.abc import Iterable
from typing import TYPE_CHECKING, BinaryIO, Literal

from robotd.config.model import MarvelmindConfig, RobotdConfig, load

if TYPE_CHECKING:
    from drivers.marvelmind.events import Counters, Event

READ_SIZE = 65536


def _address(text: str) -> int | Literal["auto"]:
    if text == "auto":
        return "auto"
    try:
        value = int(text, 0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected auto or an address 0..255, got {text!r}") from None
    if not 0 <= value <= 255:
        raise argparse.ArgumentTypeError(f"address must be 0..255, got {value}")
    return value


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `robotd ips decode` and `robotd ips listen`."""
    ips = subparsers.add_parser("ips", help="the Marvelmind indoor positioning stream: decode a capture or listen")
    actions = ips.add_subparsers(dest="ips_command", metavar="ACTION", required=True)
    decode = actions.add_parser("decode", help="decode a capture file (or - for stdin): one JSON object per event")
    decode.add_argument("file", help="raw bytes of a hedgehog's serial stream, or - for stdin")
    decode.set_defaults(handler=decode_capture)
    listen = actions.add_parser("listen", help="decode a live serial device until Ctrl-C (it is never written to)")
    listen.add_argument("device", help="serial device path or glob, e.g. /dev/serial/by-id/usb-Marvelmind*")
    listen.set_defaults(handler=listen_device)
    for action in (decode, listen):
        action.add_argument("--config", metavar="PATH", help="take the marvelmind section from this configuration")
        action.add_argument("--address", type=_address, help="hedgehog address 0..255 or auto (overrides --config)")


def _marvelmind_config(args: argparse.Namespace, device: str | None = None) -> MarvelmindConfig:
    base = (load(args.config) if args.config else RobotdConfig()).marvelmind
    return MarvelmindConfig(
        device=device or base.device,
        baudrate=base.baudrate,
        hedgehog_address=base.hedgehog_address if args.address is None else args.address,
        stale_after_s=base.stale_after_s,
        default_latency_s=base.default_latency_s,
        reconnect_max_s=base.reconnect_max_s,
    )


def _print_events(events: Iterable[Event]) -> None:
    from drivers.marvelmind.events import event_as_dict  # noqa: PLC0415 - keep `robotd --help` fast

    for event in events:
        print(json.dumps(event_as_dict(event)))
    sys.stdout.flush()


def _print_counters(counters: Counters) -> None:
    print(json.dumps({"counters": counters.as_dict()}), file=sys.stderr)


def _stdout_closed() -> None:
    """The reader of our output went away (`| head`): stop quietly, as other Unix tools do."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())  # so that the interpreter's final flush does not fail again
    os.close(devnull)


def decode_capture(args: argparse.Namespace) -> int:
    """Decode a capture; arrival times are 0.0 (a file has none), so t_meas is minus the time shift or latency."""
    from drivers.marvelmind.protocol import MarvelmindParser  # noqa: PLC0415

    config = _marvelmind_config(args)
    parser = MarvelmindParser(config.hedgehog_address, config.default_latency_s)
    try:
        source: BinaryIO = sys.stdin.buffer if args.file == "-" else open(args.file, "rb")  # noqa: SIM115
    except OSError as error:
        print(f"robotd ips decode: cannot read {args.file}: {error.strerror or error}", file=sys.stderr)
        return 66  # EX_NOINPUT
    with source:
        read = getattr(source, "read1", source.read)  # read1: a pipe's bytes are decoded as they come
        try:
            while chunk := read(READ_SIZE):
                _print_events(parser.feed(chunk, arrival=0.0))
        except BrokenPipeError:
            _stdout_closed()
    parser.finish()
    _print_counters(parser.counters)
    return 0


def listen_device(args: argparse.Namespace) -> int:
    """Decode a live device until Ctrl-C, reconnecting when it vanishes; arrival times are time.monotonic()."""
    from drivers.marvelmind.reader import MarvelmindReader  # noqa: PLC0415

    if not logging.getLogger().handlers:
        logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(name)s: %(message)s")
    reader = MarvelmindReader(_marvelmind_config(args, args.device), lambda event: _print_events([event]))
    try:
        asyncio.run(reader.run())
    except KeyboardInterrupt:
        pass
    except BrokenPipeError:
        _stdout_closed()
    finally:
        _print_counters(reader.counters)
    return 0
