"""`robotd scorecard`: every log kind the project can make, each checked against the self-calibration targets."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from robotd.commands.experiment import DEFAULT_SIM_CONFIG, MAX_WORKERS, seeded_run_plan
from robotd.sim.scenarios import SCENARIOS
from robotd.sim.variants import VARIANTS


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `robotd scorecard`."""
    card = subparsers.add_parser(
        "scorecard",
        help="check robotd's filter on every scenario, variant and libRSF kind of log against the issue's targets",
    )
    card.add_argument(
        "--out", required=True, metavar="DIR", help="directory for scorecard.md, summary.md and scorecard.json"
    )
    card.add_argument("--config", default=DEFAULT_SIM_CONFIG, help=f"configuration (default {DEFAULT_SIM_CONFIG})")
    card.add_argument("--seeds", type=int, default=3, help="seeded runs per kind of log (default 3)")
    card.add_argument("--first-seed", type=int, default=1, help="first seed (default 1)")
    card.add_argument("--loops", type=int, default=1, help="repetitions of each scenario (default 1, ~40 s)")
    card.add_argument(
        "--only",
        nargs="+",
        choices=SCENARIOS + VARIANTS,
        default=None,
        metavar="NAME",
        help="only these scenarios and variants (default all)",
    )
    card.add_argument(
        "--librsf", default=None, metavar="DIR", help="libRSF Labyrinth UWB dataset folder: adds its real odometry"
    )
    card.add_argument("--workers", type=int, default=None, help=f"processes (default: the CPUs, at most {MAX_WORKERS})")
    card.set_defaults(handler=run_scorecard_command)


def run_scorecard_command(args: argparse.Namespace) -> int:
    """Build the card, write it, print its verdicts; 2 on bad arguments."""
    from robotd.offline.scorecard import build  # noqa: PLC0415 - heavy imports only for this command
    from robotd.offline.scorecard_report import write_scorecard  # noqa: PLC0415

    plan = seeded_run_plan(args, "scorecard")
    if plan is None:
        return 2
    config, seeds, workers = plan
    started = time.perf_counter()
    card = build(
        config,
        seeds,
        args.loops,
        config_name=str(args.config),
        families=tuple(args.only) if args.only else SCENARIOS + VARIANTS,
        librsf_folder=None if args.librsf is None else Path(args.librsf),
        workers=workers,
        progress=lambda name: print(f"scoring {name} ...", file=sys.stderr, flush=True),
    )
    written = write_scorecard(card, Path(args.out))
    print(written[1].read_text(encoding="utf-8").split("\n| calibration target", 1)[0].rstrip())  # the verdicts
    print(
        f"{len(card.entries)} logs and {len(card.checks)} calibration checks in {time.perf_counter() - started:.0f} s"
    )
    print("wrote " + ", ".join(str(path) for path in written))
    return 0
