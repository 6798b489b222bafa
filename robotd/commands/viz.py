"""`robotd convert-log`: a sensor log from JSON Lines to MCAP or back, without loss."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `robotd convert-log`."""
    convert = subparsers.add_parser(
        "convert-log", help="convert a sensor log between JSON Lines and MCAP (by the suffixes: .mcap is MCAP)"
    )
    convert.add_argument("source", help="LOG.jsonl or FILE.mcap")
    convert.add_argument("target", help="FILE.mcap or LOG.jsonl (replaced if it exists)")
    convert.set_defaults(handler=run_convert_log)


def run_convert_log(args: argparse.Namespace) -> int:
    """Convert; bad lines are listed and skipped (exit 0); an unreadable input or unwritable output is one line."""
    from robotd.viz.mcaplog import McapLogError, convert, is_mcap  # noqa: PLC0415 - the SDK loads only when used

    source, target = Path(args.source), Path(args.target)
    if is_mcap(source) == is_mcap(target):
        print("robotd convert-log: one of SOURCE and TARGET must end in .mcap, the other not", file=sys.stderr)
        return 2
    if not source.is_file():
        print(f"robotd convert-log: {source}: no such file", file=sys.stderr)
        return os.EX_NOINPUT
    try:
        log, count = convert(source, target)
    except McapLogError as error:
        print(f"robotd convert-log: {source}: {error}", file=sys.stderr)
        return os.EX_NOINPUT
    except OSError as error:
        print(f"robotd convert-log: {target}: cannot write it: {error.strerror or error}", file=sys.stderr)
        return os.EX_CANTCREAT
    for problem in log.problems:
        print(f"robotd convert-log: {source}: {problem} (skipped)", file=sys.stderr)
    unknown = ", ".join(f"{n} {kind}" for kind, n in sorted(log.unknown_types.items()))
    print(f"wrote {count} events to {target}" + (f" (unknown types skipped: {unknown})" if unknown else ""))
    return 0
