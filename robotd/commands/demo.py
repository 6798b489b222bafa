"""`robotd sim` (the virtual robot and the daemon together) and `robotd demo` (the paper's square, end to end)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

DEFAULT_SIM_CONFIG = "config/sim.yaml"


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `robotd sim` and `robotd demo`."""
    sim = subparsers.add_parser(
        "sim", help="run the virtual robot and the daemon together until Ctrl-C (or SIGTERM, SIGHUP)"
    )
    sim.add_argument("--config", default=DEFAULT_SIM_CONFIG, help=f"configuration (default {DEFAULT_SIM_CONFIG})")
    sim.add_argument("--seed", type=int, default=None, help="the virtual robot's seed (default sim.seed)")
    sim.add_argument("--out", default="out/sim", help="folder for logs and the daemon's sensor log (default out/sim)")
    sim.add_argument(
        "--robots", type=int, default=1, metavar="N", help="a virtual fleet: N robots and an MQTT broker (default 1)"
    )
    sim.set_defaults(handler=run_sim)
    demo = subparsers.add_parser(
        "demo", help="drive the paper's square on the virtual robot through the daemon; figures and results table"
    )
    demo.add_argument("--config", default=DEFAULT_SIM_CONFIG, help=f"configuration (default {DEFAULT_SIM_CONFIG})")
    demo.add_argument("--loops", type=int, default=1, help="times round the square (default 1)")
    demo.add_argument("--side", type=float, default=3.0, help="side of the square in metres (default 3)")
    demo.add_argument("--speed", type=float, default=0.3, help="driving speed in m/s (default 0.3)")
    demo.add_argument("--seed", type=int, default=None, help="the virtual robot's seed (default sim.seed)")
    demo.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    demo.set_defaults(handler=run_demo_command)


def run_sim(args: argparse.Namespace) -> int:
    """Run `robotd vhw` and `robotd run` on a private copy of the configuration until a stop signal (exit 0) or the
    daemon's end (exit 1); no child outlives it."""
    import time  # noqa: PLC0415

    from robotd.config.model import load  # noqa: PLC0415
    from robotd.tools.demo import StopRequested, private_config, running_robot, stop_signals  # noqa: PLC0415

    if args.robots != 1:
        from robotd.tools.fleet_sim import run_fleet_sim  # noqa: PLC0415

        if args.robots < 1:
            print(f"robotd sim: --robots must be at least 1, got {args.robots}", file=sys.stderr)
            return 2
        return run_fleet_sim(Path(args.config), Path(args.out), args.robots, args.seed)
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    from robotd.tools.demo import free_tcp_port  # noqa: PLC0415

    # the live view on: the virtual robot is where a person first looks at robotd
    config_path = private_config(Path(args.config), out, {"viewer": {"enabled": True, "port": free_tcp_port()}})
    stopped: list[tuple[str, int]] = []
    try:
        with stop_signals(), running_robot(config_path, out, args.seed, stopped) as (_children, recorder):
            config = load(config_path)
            print(f"robotd sim: running; config {config_path}")
            print(f"  teleop:      robotd teleop --config {config_path}")
            print(f"  pose stream: robotd pose --socket {config.pose_socket.path}")
            print(
                f"  live view:   ws://127.0.0.1:{config.viewer.port} (Foxglove: Open connection > Foxglove WebSocket)"
            )
            print(f"  logs:        {out}/daemon.log, {out}/vhw.log; sensor log {out}/run.jsonl, {out}/run.mcap")
            print("Ctrl-C stops both.", flush=True)
            while recorder.is_alive():
                time.sleep(0.5)
    except StopRequested as request:
        print(f"\nrobotd sim: {request}: stopped {_statuses(stopped)}", flush=True)
        return 0
    except RuntimeError as error:  # a child ended while starting
        print(
            f"robotd sim: {error}; stopped {_statuses(stopped)}; see {out}/daemon.log, {out}/vhw.log", file=sys.stderr
        )
        return 1
    print(f"robotd sim: the daemon closed its pose socket; stopped {_statuses(stopped)}; see {out}/daemon.log")
    return 1


def _statuses(stopped: list[tuple[str, int]]) -> str:
    """`robotd run` (exit 0), `robotd vhw` (exit 0), in the order they were stopped."""
    return ", ".join(f"{name} (exit {status})" for name, status in stopped) or "nothing (none had started)"


def run_demo_command(args: argparse.Namespace) -> int:
    """Run the demo and print where its results are; 128 + the signal's number after a stop signal."""
    from robotd.tools.demo import DemoPlan, StopRequested, run_demo, stop_signals  # noqa: PLC0415

    if args.loops < 1 or args.side <= 0 or args.speed <= 0:
        print("robotd demo: --loops must be >= 1, --side and --speed > 0", file=sys.stderr)
        return 2
    try:
        with stop_signals():
            run_demo(Path(args.config), Path(args.out), DemoPlan(args.loops, args.side, args.speed, seed=args.seed))
    except RuntimeError as error:
        print(f"\nrobotd demo: {error}", file=sys.stderr)
        return 1
    except StopRequested as request:
        print(f"\nrobotd demo: {request}: every process it started has been stopped", file=sys.stderr)
        return 128 + request.signum
    return 0
