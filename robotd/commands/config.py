"""`robotd check-config` and `robotd config-reference`."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from robotd.config.model import config_reference, load
from robotd.readme import current


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add the configuration sub-commands."""
    check = subparsers.add_parser("check-config", help="validate a configuration file (exit 78 when it is bad)")
    check.add_argument("path", help="YAML configuration file")
    check.add_argument(
        "--schema-only",
        action="store_true",
        help="check the file alone, not the key file and address it names (for a configuration of another machine)",
    )
    check.set_defaults(handler=check_config)
    ref = subparsers.add_parser("config-reference", help="print the Markdown reference of every configuration key")
    ref.set_defaults(handler=print_reference)
    readme = subparsers.add_parser("readme", help="bring the README's generated blocks up to date (or --check them)")
    readme.add_argument("path", nargs="?", default="README.md", help="the README (default README.md)")
    readme.add_argument("--check", action="store_true", help="exit 1 when a block is stale, change nothing")
    readme.set_defaults(handler=update_readme)


def check_config(args: argparse.Namespace) -> int:
    """Validate the file, then what it names on this host (as `robotd run` does); errors are ConfigError (exit 78)."""
    from robotd.daemon.preflight import preflight  # noqa: PLC0415 - keeps `robotd --help` fast (imports teleop)

    config = load(args.path)
    if not args.schema_only:
        preflight(config)
    print(f"{args.path}: ok")
    return 0


def print_reference(_args: argparse.Namespace) -> int:
    """Print the configuration reference."""
    print(config_reference(), end="")
    return 0


def update_readme(args: argparse.Namespace) -> int:
    """Rewrite (or check) the generated blocks of the README from their sources."""
    path = Path(args.path)
    text = path.read_text(encoding="utf-8")
    try:
        fresh = current(text, path.resolve().parent)
    except ValueError as error:
        print(f"robotd readme: {path}: {error}", file=sys.stderr)
        return 1
    if args.check:
        if fresh != text:
            print(f"robotd readme: {path} is stale: run `robotd readme`", file=sys.stderr)
            return 1
        return 0
    path.write_text(fresh, encoding="utf-8")
    return 0
