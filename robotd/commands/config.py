"""`robotd check-config` and `robotd config-reference`."""

from __future__ import annotations

import argparse

from robotd.config import config_reference, load


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add the configuration sub-commands."""
    check = subparsers.add_parser("check-config", help="validate a configuration file (exit 78 when it is bad)")
    check.add_argument("path", help="YAML configuration file")
    check.set_defaults(handler=check_config)
    ref = subparsers.add_parser("config-reference", help="print the Markdown reference of every configuration key")
    ref.set_defaults(handler=print_reference)


def check_config(args: argparse.Namespace) -> int:
    """Validate the file named on the command line; errors surface as ConfigError (exit 78)."""
    load(args.path)
    print(f"{args.path}: ok")
    return 0


def print_reference(_args: argparse.Namespace) -> int:
    """Print the configuration reference."""
    print(config_reference(), end="")
    return 0
