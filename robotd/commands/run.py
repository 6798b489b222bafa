"""`robotd run`: the daemon, as systemd starts it on the Pi."""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path

from robotd.config.model import load

DEFAULT_CONFIG = "/etc/robotd/robot.yaml"


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `robotd run`."""
    run = subparsers.add_parser("run", help="run the daemon: odometry + IPS fusion, teleop, pose socket")
    run.add_argument("--config", default=DEFAULT_CONFIG, help=f"configuration file (default {DEFAULT_CONFIG})")
    run.add_argument(
        "--record",
        metavar="LOG.jsonl|FILE.mcap",
        action="append",
        default=[],
        help="write every sensor event to this sensor log; FILE.mcap: as MCAP, with what the daemon publishes to the"
        " live view (give both to record both); an existing file is kept (LOG.1.jsonl... is written instead)",
    )
    run.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    run.set_defaults(handler=run_daemon_command)


def configure_logging(verbose: bool) -> None:
    """Log to stderr, one line a message (journald adds the time stamps)."""
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO, format="%(name)s: %(levelname)s: %(message)s", force=True
    )


def run_daemon_command(args: argparse.Namespace) -> int:
    """Validate the configuration (exit 78 when bad), then run the daemon until stopped."""
    from robotd.daemon.preflight import preflight  # noqa: PLC0415
    from robotd.daemon.recorder import RecordingError  # noqa: PLC0415 - same
    from robotd.daemon.service import run_daemon  # noqa: PLC0415 - keeps `robotd --help` fast

    config = load(args.config)
    records = _records(args.record)
    if isinstance(records, str):
        print(f"robotd run: --record: {records}", file=sys.stderr)
        return 2
    preflight(config)  # the key file and the bind address, as `robotd check-config` checks them
    configure_logging(args.verbose)
    try:
        return run_daemon(config, records.get(".jsonl"), records.get(".mcap"))
    except RecordingError as error:  # before anything started: nothing to stop
        print(f"robotd run: --record: {error}", file=sys.stderr)
        return os.EX_CANTCREAT


def _records(paths: list[str]) -> dict[str, Path] | str:
    """The recordings asked for by kind (".jsonl": anything but .mcap, ".mcap"), or why they cannot be made."""
    records: dict[str, Path] = {}
    for path in map(Path, paths):
        kind = ".mcap" if path.suffix == ".mcap" else ".jsonl"
        if kind in records:
            return f"one {kind} recording at most, got {records[kind]} and {path}"
        records[kind] = path
    return records
