"""`robotd replay` (a sensor log through odometry, the paper's filter, a gated EKF and robotd's) and `robotd
convert-librsf`."""

from __future__ import annotations

import argparse
import os
import re
import sys
import time
from pathlib import Path

from robotd.config.model import RobotdConfig, load, parse
from robotd.daemon import calibration_store
from robotd.logs import logcheck
from robotd.logs.sensorlog import SensorLog
from robotd.offline import librsf
from robotd.offline.replay import format_table, replay, robot_from_log, write_outputs
from robotd.viz.mcaplog import read_any_log

# sysexits.h: what a script calling `robotd replay` can tell apart
SHOWN_PROBLEMS = 20  # bad lines listed one by one; beyond, one line counts the rest


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `robotd replay` and `robotd convert-librsf`."""
    rep = subparsers.add_parser(
        "replay",
        help="replay a sensor log through odometry, the paper's EKF, a gated EKF and robotd's EKF; score against truth",
    )
    rep.add_argument("log", help="sensor log (JSON Lines, or an MCAP file: .mcap)")
    rep.add_argument("--out", required=True, help="directory for estimates.jsonl, calibration.json and metrics.json")
    rep.add_argument("--config", help="YAML configuration (default: built-in defaults); meta.robot overrides geometry")
    rep.add_argument(
        "--calibration",
        metavar="FILE",
        help="start robotd's filter from this calibration file (the daemon's ekf.calibration_file, or a replay's"
        " calibration.json), as the daemon starts after a restart",
    )
    add_sort_option(rep)
    rep.add_argument("--mcap", metavar="FILE.mcap", help="also write the log and every method's poses as MCAP")
    rep.add_argument(
        "--view",
        nargs="?",
        const=8765,
        type=int,
        metavar="PORT",
        help="then serve the replay to Foxglove on 127.0.0.1:PORT (8765) with playback controls, until Ctrl-C",
    )
    rep.set_defaults(handler=run_replay)
    conv = subparsers.add_parser(
        "convert-librsf", help="convert the libRSF Labyrinth UWB dataset folder (CSV) to a sensor log"
    )
    conv.add_argument("folder", help="dataset folder (wheel_odometry.csv, derived_multilateration_fixes.csv, ...)")
    conv.add_argument("--out", required=True, help="sensor log to write")
    conv.set_defaults(handler=run_convert)


def run_replay(args: argparse.Namespace) -> int:
    """Replay the log, write the outputs, print the table; bad lines are skipped and listed on stderr (exit 0), a log
    that cannot be replayed or read and an output that cannot be written give one line and a sysexits status."""
    config: RobotdConfig = load(args.config) if args.config else parse("")
    started = time.perf_counter()
    out = Path(args.out)
    try:  # before the replay: a bad --out should not cost a whole replay first
        out.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        why = "a file is in the way" if isinstance(error, FileExistsError) else error.strerror or str(error)
        print(f"robotd replay: --out {out}: cannot make it a directory: {why}", file=sys.stderr)
        return os.EX_CANTCREAT
    start = None
    if args.calibration:
        try:
            start = calibration_store.read(args.calibration)
        except OSError as error:
            print(f"robotd replay: --calibration {args.calibration}: {error.strerror or error}", file=sys.stderr)
            return os.EX_NOINPUT
        except ValueError as error:
            print(f"robotd replay: --calibration {args.calibration}: {error}", file=sys.stderr)
            return os.EX_DATAERR
    try:
        log = read_any_log(args.log)
    except OSError as error:
        print(f"robotd replay: {args.log}: {error.strerror or error}", file=sys.stderr)
        return os.EX_NOINPUT
    read_problems = log.problems
    log = in_order_if_asked(log, f"robotd replay: {args.log}", sort=args.sort)
    try:
        log, checked_problems, notes = logcheck.check(log, robot_from_log(log, config)[2])
    except logcheck.LogRefusedError as refusal:
        _report(args.log, [*read_problems, *refusal.problems])
        print(f"robotd replay: {args.log}: {refusal}; nothing replayed", file=sys.stderr)
        return os.EX_DATAERR
    _report(args.log, [*read_problems, *checked_problems])
    for note in notes:
        print(f"robotd replay: {args.log}: {note}", file=sys.stderr)
    result = replay(log, config, start)
    for problem in result.problems[len(log.problems) :]:
        print(f"robotd replay: {problem}", file=sys.stderr)
    try:
        written = write_outputs(result, out)
    except OSError as error:
        print(f"robotd replay: --out {out}: cannot write the outputs: {error}", file=sys.stderr)
        return os.EX_IOERR
    elapsed = time.perf_counter() - started
    print(format_table(result))
    if log.events:
        span = log.events[-1].t - log.events[0].t
        rate = span / max(elapsed, 1e-9)
        print(f"{len(log.events)} events, {span:.1f} s of log in {elapsed:.2f} s ({rate:.0f}x real time)")
    if args.mcap or args.view is not None:
        from robotd.offline.replay_mcap import write_and_view  # noqa: PLC0415 - the SDK loads only when asked for

        return write_and_view(log, result, config, out=out, mcap=args.mcap, view_port=args.view, written=written)
    print("wrote " + ", ".join(str(path) for path in written))
    return 0


def add_sort_option(parser: argparse.ArgumentParser) -> None:
    """--sort, for the commands that read sensor logs (robotd.logs.logcheck.in_time_order)."""
    parser.add_argument(
        "--sort",
        action="store_true",
        help="take a log whose lines are not in time order (a merge of recordings) in the order of their times;"
        " without it such a log is refused, as its arrival order is not known",
    )


def in_order_if_asked(log: SensorLog, where: str, *, sort: bool) -> SensorLog:
    """The log, in the order of its times when --sort asked for it; says on stderr how many lines came late."""
    if not sort:
        return log
    log, late = logcheck.in_time_order(log)
    if late:
        print(f"{where}: {late} lines came after a later time: taken in time order (--sort)", file=sys.stderr)
    return log


def _report(log: str, problems: list[str]) -> None:
    """The bad lines skipped, in file order: the first SHOWN_PROBLEMS one a line, then how many more."""
    ordered = sorted(problems, key=_line_number)
    for problem in ordered[:SHOWN_PROBLEMS]:
        print(f"robotd replay: {log}: {problem} (skipped)", file=sys.stderr)
    if len(ordered) > SHOWN_PROBLEMS:
        print(
            f"robotd replay: {log}: ... and {len(ordered) - SHOWN_PROBLEMS} more bad lines (skipped)", file=sys.stderr
        )


def _line_number(problem: str) -> int:
    match = re.match(r"(?:line|event) (\d+)", problem)
    return int(match.group(1)) if match else 0


def run_convert(args: argparse.Namespace) -> int:
    """Convert the dataset; 1 when it cannot be read, 73 when the log cannot be written."""
    try:
        count = librsf.write(Path(args.folder), Path(args.out))
    except librsf.DatasetError as error:
        print(f"robotd convert-librsf: {error}", file=sys.stderr)
        return 1
    except OSError as error:
        print(f"robotd convert-librsf: --out {args.out}: {error.strerror or error}", file=sys.stderr)
        return os.EX_CANTCREAT
    print(f"wrote {count} events to {args.out}")
    return 0
