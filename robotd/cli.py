"""The `robotd` command line: argparse sub-commands, each registered by one module of `robotd.commands`.

A bad configuration anywhere ends the program with exit status 78 (EX_CONFIG) and one line per problem,
never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from robotd import __version__
from robotd.config.schema import ConfigError

EX_CONFIG = 78

# Each module has `register(subparsers)`, which adds its sub-commands with a `handler(args) -> int` default.
COMMAND_MODULES = (
    "robotd.commands.config",
    "robotd.commands.bench",
    "robotd.commands.ips",
    "robotd.commands.teleop",
    "robotd.commands.pose",
    "robotd.commands.wheels",
    "robotd.commands.sim",
    "robotd.commands.replay",
    "robotd.commands.experiment",
    "robotd.commands.scorecard",
    "robotd.commands.tune",
    "robotd.commands.run",
    "robotd.commands.demo",
    "robotd.commands.install",
    "robotd.commands.doctor",
    "robotd.commands.viz",
    "robotd.commands.fleet",
)


def build_parser() -> argparse.ArgumentParser:
    """The full argument parser with every sub-command."""
    parser = argparse.ArgumentParser(
        prog="robotd",
        description="Localisation daemon for a four-mecanum-wheel robot: odometry + Marvelmind IPS fused by an EKF.",
    )
    parser.add_argument("--version", action="version", version=f"robotd {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status."""
    args = build_parser().parse_args(argv)
    try:
        status: int = args.handler(args)
    except ConfigError as error:
        for problem in error.problems:
            print(f"robotd: config: {problem}", file=sys.stderr)
        return EX_CONFIG
    except KeyboardInterrupt:
        return 130
    return status
