"""`robotd simulate` (a scenario as a sensor log, offline) and `robotd vhw` (the virtual robot, live)."""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from robotd.config.model import WHEELS, load
from robotd.sim.refix import KINDS
from robotd.sim.scenarios import SCENARIOS
from robotd.sim.variants import VARIANTS

DEFAULT_SIM_CONFIG = "config/sim.yaml"


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add the simulator's sub-commands."""
    simulate = subparsers.add_parser(
        "simulate", help="run a scenario on the virtual robot in simulated time and write its sensor log with truth"
    )
    simulate.add_argument("scenario", choices=SCENARIOS + VARIANTS, help="what the remote control does")
    simulate.add_argument("--out", required=True, metavar="LOG.jsonl", help="sensor log to write")
    simulate.add_argument("--seed", type=int, default=None, help="seed (default: the configuration's sim.seed)")
    simulate.add_argument("--loops", type=int, default=3, help="repetitions of the scenario (default 3)")
    simulate.add_argument("--config", default=DEFAULT_SIM_CONFIG, help=f"configuration (default {DEFAULT_SIM_CONFIG})")
    simulate.set_defaults(handler=run_simulate)
    refix = subparsers.add_parser(
        "simulate-fixes",
        help="replace a recorded log's IPS fixes by the virtual hedgehog's, measured on its truth (real odometry, "
        "simulated fixes: how the logs robotd is judged on are made)",
    )
    refix.add_argument("log", help="sensor log with truth (JSON Lines), e.g. a real robot's with motion capture")
    refix.add_argument("--out", required=True, metavar="LOG.jsonl", help="sensor log to write")
    refix.add_argument(
        "--kind",
        choices=KINDS,
        default="clean",
        help="clean (default); untimed: no measurement times; harsh: outlier bursts, an 8 s outage, untimed",
    )
    refix.add_argument("--seed", type=int, default=None, help="seed (default: the configuration's sim.seed)")
    refix.add_argument(
        "--config",
        default=DEFAULT_SIM_CONFIG,
        help=f"the hedgehog's rate, latency and noise: sim.ips_* (default {DEFAULT_SIM_CONFIG})",
    )
    refix.set_defaults(handler=run_simulate_fixes)
    vhw = subparsers.add_parser(
        "vhw", help="run the virtual robot in real time: a virtual pigpiod, a Marvelmind pseudo-terminal, physics"
    )
    vhw.add_argument("--config", default=DEFAULT_SIM_CONFIG, help=f"configuration (default {DEFAULT_SIM_CONFIG})")
    vhw.add_argument("--seed", type=int, default=None, help="seed (default: the configuration's sim.seed)")
    vhw.add_argument("--duration", type=float, default=None, metavar="S", help="stop after this many seconds")
    vhw.add_argument(
        "--record",
        default=None,
        metavar="LOG.jsonl",
        help="sensor log of truth, ticks and fixes (default sim.record_path)",
    )
    vhw.add_argument(
        "--swap-encoders",
        nargs=2,
        choices=WHEELS,
        default=(),
        metavar="WHEEL",
        help="wire it wrong: cross these two wheels' encoder cables (for robotd doctor)",
    )
    vhw.add_argument(
        "--reverse-motor",
        action="append",
        choices=WHEELS,
        default=[],
        metavar="WHEEL",
        help="wire it wrong: swap this wheel's motor leads (repeatable; for robotd doctor)",
    )
    vhw.set_defaults(handler=run_vhw)


def run_simulate(args: argparse.Namespace) -> int:
    """Write the scenario's sensor log; prints what it wrote and how much faster than real time it ran."""
    from robotd.sim.offline import simulate  # noqa: PLC0415 - the simulator is not needed by other commands

    config = load(args.config)
    seed = config.sim.seed if args.seed is None else args.seed
    if args.loops < 1:
        print(f"robotd simulate: --loops must be at least 1, got {args.loops}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    with out.open("w", encoding="utf-8") as stream:
        summary = simulate(config, args.scenario, seed, args.loops, stream)
    elapsed = time.perf_counter() - started
    counts = ", ".join(f"{n} {kind}" for kind, n in sorted(summary.events.items()))
    print(f"{out}: {args.scenario}, seed {seed}, {args.loops} loops, {summary.simulated_s:.1f} s simulated ({counts})")
    print(f"ran in {elapsed:.2f} s: {summary.simulated_s / max(elapsed, 1e-9):.0f}x real time")
    return 0


def run_simulate_fixes(args: argparse.Namespace) -> int:
    """Write the log with simulated fixes; a log that cannot be read or has no usable truth gives one line and a
    sysexits status (66, 65), an output that cannot be written 73."""
    from robotd.logs.sensorlog import IpsFix, LogWriter, Meta, read_log  # noqa: PLC0415 - only this one writes logs
    from robotd.offline.replay import beacon_offset  # noqa: PLC0415 - read as robotd replay reads it
    from robotd.sim.refix import TruthError, refixed  # noqa: PLC0415 - nor simulates fixes
    from robotd.sim.world import ips_params  # noqa: PLC0415

    config = load(args.config)
    seed = config.sim.seed if args.seed is None else args.seed
    try:
        log = read_log(args.log)
    except OSError as error:
        print(f"robotd simulate-fixes: {args.log}: {error.strerror or error}", file=sys.stderr)
        return os.EX_NOINPUT
    offset, problem = beacon_offset(log, config)
    if problem is not None:  # fixes of a beacon placed by a guess would be worth nothing
        print(f"robotd simulate-fixes: {args.log}: {problem}", file=sys.stderr)
        return os.EX_DATAERR
    try:
        events = refixed(log.events, ips_params(config.sim), args.kind, seed, offset)
    except TruthError as error:
        print(f"robotd simulate-fixes: {args.log}: {error}", file=sys.stderr)
        return os.EX_DATAERR
    source = f"{log.meta.source}; fixes: robotd simulate-fixes --kind {args.kind} --seed {seed}".lstrip("; ")
    out = Path(args.out)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        with out.open("w", encoding="utf-8") as stream:
            writer = LogWriter(stream, Meta(robot=log.meta.robot, source=source))
            for event in events:
                writer.write(event)
    except OSError as error:
        print(f"robotd simulate-fixes: --out {out}: {error.strerror or error}", file=sys.stderr)
        return os.EX_CANTCREAT
    fixes = sum(1 for event in events if isinstance(event, IpsFix))
    print(f"{out}: {args.log}'s odometry and truth, {fixes} {args.kind} fixes (seed {seed}) from the virtual hedgehog")
    return 0


def run_vhw(args: argparse.Namespace) -> int:
    """Run the virtual hardware until interrupted (or for --duration seconds)."""
    import asyncio  # noqa: PLC0415

    from robotd.sim.live import Miswiring, run_virtual_hardware  # noqa: PLC0415

    config = load(args.config)
    seed = config.sim.seed if args.seed is None else args.seed
    record = config.sim.record_path if args.record is None else args.record
    if len(set(args.swap_encoders)) == 1:
        print("robotd vhw: --swap-encoders needs two different wheels", file=sys.stderr)
        return 2
    miswiring = Miswiring.of(args.swap_encoders, args.reverse_motor)
    try:
        asyncio.run(
            run_virtual_hardware(
                config, seed, duration_s=args.duration, record_path=record or None, miswiring=miswiring
            )
        )
    except KeyboardInterrupt:
        return 0
    return 0
