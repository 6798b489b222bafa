"""`robotd experiment`: a scenario over seeded offline runs, scored and summarised, with the paper's figures."""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from robotd.config.model import RobotdConfig, load
from robotd.sim.scenarios import SCENARIOS
from robotd.sim.variants import VARIANTS

DEFAULT_SIM_CONFIG = "config/sim.yaml"
MAX_WORKERS = 2


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `robotd experiment`."""
    exp = subparsers.add_parser(
        "experiment",
        help="run a scenario offline over seeds; write results.md, results.json and the paper's Fig. 6 and 7",
    )
    exp.add_argument("scenario", choices=SCENARIOS + VARIANTS, help="what the remote control does")
    exp.add_argument("--loops", type=int, default=3, help="repetitions of the scenario per run (default 3)")
    exp.add_argument("--seeds", type=int, default=10, help="number of seeded runs (default 10)")
    exp.add_argument("--first-seed", type=int, default=None, help="first seed (default: the configuration's sim.seed)")
    exp.add_argument("--out", required=True, metavar="DIR", help="directory for the results and figures")
    exp.add_argument("--config", default=DEFAULT_SIM_CONFIG, help=f"configuration (default {DEFAULT_SIM_CONFIG})")
    exp.add_argument(
        "--librsf", default=None, metavar="DIR", help="libRSF Labyrinth UWB dataset folder: adds the real-data row"
    )
    exp.add_argument(
        "--workers",
        type=int,
        default=None,
        help=f"processes running seeds (default: the CPUs, at most {MAX_WORKERS}); results do not depend on it",
    )
    exp.add_argument("--all-figures", action="store_true", help="draw the figures of every seed, not only the first")
    exp.add_argument("--keep-logs", action="store_true", help="also write each seed's sensor log to DIR/logs/")
    exp.set_defaults(handler=run_experiment_command)


def seeded_run_plan(args: argparse.Namespace, command: str) -> tuple[RobotdConfig, list[int], int] | None:
    """The configuration `--config` names (loaded once), and the seeds and worker processes that `--seeds`,
    `--first-seed` (default: the configuration's `sim.seed`) and `--workers` ask for; None, after saying why on
    stderr, when `--loops` or `--seeds` is below 1."""
    for name in ("loops", "seeds"):
        if getattr(args, name) < 1:
            print(f"robotd {command}: --{name} must be at least 1, got {getattr(args, name)}", file=sys.stderr)
            return None
    config = load(args.config)
    first = config.sim.seed if args.first_seed is None else args.first_seed
    workers = args.workers if args.workers is not None else min(MAX_WORKERS, os.cpu_count() or 1)
    return config, list(range(first, first + args.seeds)), max(1, workers)


def run_experiment_command(args: argparse.Namespace) -> int:
    """Run the experiment, write its outputs, print the summary and how long it took; 2 on bad arguments."""
    from robotd.offline.experiment import run_experiment  # noqa: PLC0415 - heavy imports only for this command
    from robotd.offline.experiment_report import write_results  # noqa: PLC0415

    plan = seeded_run_plan(args, "experiment")
    if plan is None:
        return 2
    config, seeds, workers = plan
    out = Path(args.out)
    started = time.perf_counter()
    exp = run_experiment(
        config,
        args.scenario,
        seeds,
        args.loops,
        config_name=str(args.config),
        workers=workers,
        librsf_folder=None if args.librsf is None else Path(args.librsf),
        figure_seeds=frozenset(seeds) if args.all_figures else None,
        log_dir=out / "logs" if args.keep_logs else None,
    )
    written = write_results(exp, out)
    elapsed = time.perf_counter() - started
    if exp.real is None and args.librsf is not None:
        print(f"robotd experiment: {exp.real_note}", file=sys.stderr)
    text = written[0].read_text(encoding="utf-8")
    print(text.split("\n### ", 1)[0].rstrip())  # the summary table and the verdict; the rest is in the file
    simulated = sum(run.duration_s for run in exp.runs)
    print(
        f"{len(seeds)} runs, {simulated:.0f} s simulated in {elapsed:.1f} s "
        f"({simulated / max(elapsed, 1e-9):.0f}x real time, {workers} worker(s))"
    )
    print("wrote " + ", ".join(str(path) for path in written))
    return 0
