"""`robotd check-config` and `robotd config-reference`."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from robotd.config import config_reference, load


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add the configuration sub-commands."""
    check = subparsers.add_parser("check-config", help="validate a configuration file (exit 78 when it is bad)")
    check.add_argument("path", help="YAML configuration file")
    check.set_defaults(handler=check_config)
    ref = subparsers.add_parser("config-reference", help="print the Markdown reference of every configuration key")
    ref.add_argument("--update", metavar="README", help="rewrite the reference between the markers of this file")
    ref.set_defaults(handler=print_reference)


def check_config(args: argparse.Namespace) -> int:
    """Validate the file named on the command line; errors surface as ConfigError (exit 78)."""
    load(args.path)
    print(f"{args.path}: ok")
    return 0


START, END = "<!-- config-reference:start -->", "<!-- config-reference:end -->"


def print_reference(args: argparse.Namespace) -> int:
    """Print the configuration reference, or splice it into a Markdown file between its markers."""
    if not args.update:
        print(config_reference(), end="")
        return 0
    path = Path(args.update)
    text = path.read_text(encoding="utf-8")
    head, start, rest = text.partition(START)
    _, end, tail = rest.partition(END)
    if not start or not end:
        print(f"robotd: {path} has no {START} ... {END} markers", file=sys.stderr)
        return 1
    path.write_text(f"{head}{START}\n{config_reference()}{END}{tail}", encoding="utf-8")
    return 0
