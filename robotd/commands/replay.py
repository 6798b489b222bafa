"""`robotd replay` (a sensor log through odometry, the paper's filter and robotd's) and `robotd convert-librsf`."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from robotd import librsf
from robotd.config import RobotdConfig, load, parse
from robotd.logfile import read_log
from robotd.replay import format_table, replay, write_outputs


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `robotd replay` and `robotd convert-librsf`."""
    rep = subparsers.add_parser(
        "replay", help="replay a sensor log through odometry, the paper's EKF and robotd's EKF; score against truth"
    )
    rep.add_argument("log", help="sensor log (JSON Lines)")
    rep.add_argument("--out", required=True, help="directory for estimates.jsonl and metrics.json")
    rep.add_argument("--config", help="YAML configuration (default: built-in defaults); meta.robot overrides geometry")
    rep.set_defaults(handler=run_replay)
    conv = subparsers.add_parser(
        "convert-librsf", help="convert the libRSF Labyrinth UWB dataset folder (CSV) to a sensor log"
    )
    conv.add_argument("folder", help="dataset folder (wheel_odometry.csv, derived_multilateration_fixes.csv, ...)")
    conv.add_argument("--out", required=True, help="sensor log to write")
    conv.set_defaults(handler=run_convert)


def run_replay(args: argparse.Namespace) -> int:
    """Replay the log, write the outputs, print the table; 1 when the log cannot be read."""
    config: RobotdConfig = load(args.config) if args.config else parse("")
    started = time.perf_counter()
    try:
        log = read_log(args.log)
    except OSError as error:
        print(f"robotd replay: {args.log}: {error}", file=sys.stderr)
        return 1
    for problem in log.problems:
        print(f"robotd replay: {args.log}: {problem} (skipped)", file=sys.stderr)
    result = replay(log, config)
    for problem in result.problems[len(log.problems) :]:
        print(f"robotd replay: {problem}", file=sys.stderr)
    written = write_outputs(result, Path(args.out))
    elapsed = time.perf_counter() - started
    print(format_table(result))
    if log.events:
        span = log.events[-1].t - log.events[0].t
        rate = span / max(elapsed, 1e-9)
        print(f"{len(log.events)} events, {span:.1f} s of log in {elapsed:.2f} s ({rate:.0f}x real time)")
    print("wrote " + ", ".join(str(path) for path in written))
    return 0


def run_convert(args: argparse.Namespace) -> int:
    """Convert the dataset; 1 when it cannot be read."""
    try:
        count = librsf.write(Path(args.folder), Path(args.out))
    except librsf.DatasetError as error:
        print(f"robotd convert-librsf: {error}", file=sys.stderr)
        return 1
    print(f"wrote {count} events to {args.out}")
    return 0
