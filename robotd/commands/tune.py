"""`robotd tune LOG...`: fit the filter's noise parameters, odometry calibration and lever arm to recorded logs."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from robotd.commands.replay import add_sort_option, in_order_if_asked
from robotd.config.model import RobotdConfig, load, parse
from robotd.logs import logcheck
from robotd.logs.sensorlog import SensorLog, read_log


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `robotd tune`."""
    tune = subparsers.add_parser(
        "tune",
        help="fit the filter's noise and odometry calibration (on request the beacon's lever arm) to sensor logs (no"
        " truth needed); write a YAML snippet",
    )
    tune.add_argument("logs", nargs="+", metavar="LOG", help="sensor logs (JSON Lines)")
    tune.add_argument("--config", help="YAML configuration to start from (default: built-in defaults)")
    tune.add_argument("--out", metavar="FILE.yaml", help="write the YAML snippet here (default: print it)")
    add_sort_option(tune)
    tune.add_argument(
        "--lever-arm",
        action="store_true",
        help="fit the beacon's lever arm too (robot.ips_offset_m; from logs in which the robot turned): for a lever arm"
        " not measured; a radio's bias that turns with the robot can look like one",
    )
    tune.set_defaults(handler=run_tune)


def run_tune(args: argparse.Namespace) -> int:
    """Tune, print what changed and why, write the snippet; a log that cannot be read or used: one line, sysexits."""
    from robotd.offline.replay import robot_from_log  # noqa: PLC0415 - heavy imports only for this command
    from robotd.offline.tune import tune, yaml_snippet  # noqa: PLC0415

    config: RobotdConfig = load(args.config) if args.config else parse("")
    logs: list[SensorLog] = []
    for path in args.logs:
        try:
            log = read_log(path)
        except OSError as error:
            print(f"robotd tune: {path}: {error.strerror or error}", file=sys.stderr)
            return os.EX_NOINPUT
        log = in_order_if_asked(log, f"robotd tune: {path}", sort=args.sort)
        try:
            log = logcheck.check(log, robot_from_log(log, config)[2]).log
        except logcheck.LogRefusedError as refusal:
            print(f"robotd tune: {path}: {refusal}", file=sys.stderr)
            return os.EX_DATAERR
        logs.append(log)
    result = tune(logs, config, lever_arm=args.lever_arm)
    for path, before, after in zip(args.logs, result.before, result.after, strict=True):
        print(
            f"{path}: {after.fixes} fixes; innovations' negative log likelihood per fix {before.nll:.3f} -> "
            f"{after.nll:.3f}, NIS mean {before.nis_mean:.2f} -> {after.nis_mean:.2f} (2 when the noise is right)"
        )
    print("changed (each kept because it made the fixes more likely):" if result.changes else "nothing to change")
    for change in result.changes:
        print(f"  {change}")
    for note in result.notes:
        print(note)
    snippet = yaml_snippet(result)
    if args.out:
        try:
            Path(args.out).write_text(snippet, encoding="utf-8")
        except OSError as error:
            print(f"robotd tune: --out {args.out}: {error.strerror or error}", file=sys.stderr)
            return os.EX_IOERR
        print(f"wrote {args.out}")
    else:
        print(snippet, end="")
    return 0
