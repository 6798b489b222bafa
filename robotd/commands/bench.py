"""`robotd bench`: performance figures, each as a ratio against its named baseline."""

from __future__ import annotations

import argparse
import contextlib
import importlib
import io
import json
import os
import platform
import sys
import time
from types import ModuleType
from typing import TextIO

from robotd.bench import BENCHMARK_ADDITIONS, BENCHMARK_MODULES


class _Tee(io.TextIOBase):
    """Writes through to a stream and keeps a copy."""

    def __init__(self, stream: TextIO) -> None:
        self._stream = stream
        self._copy = io.StringIO()

    def write(self, text: str) -> int:
        self._stream.write(text)
        self._stream.flush()
        return self._copy.write(text)

    def text(self) -> str:
        """Everything written so far."""
        return self._copy.getvalue()


def _report(printed: dict[str, str], modules: dict[str, ModuleType], *, quick: bool) -> str:
    """The Markdown benchmark report: the machine, then what each benchmark printed, verbatim."""
    machine = f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, {platform.system()}"
    lines = [f"Measured by `robotd bench{' --quick' if quick else ''}` on {machine}, {time.strftime('%Y-%m-%d')}.", ""]
    for name, text in printed.items():
        doc = (modules[name].__doc__ or "").strip().splitlines()[0]
        lines += [f"**`robotd bench {name}`**: {doc}", "", "```", text.rstrip(), "```", ""]
    return "\n".join(lines)


def _modules() -> dict[str, ModuleType]:
    modules = [importlib.import_module(name) for name in BENCHMARK_MODULES]
    return {module.NAME: module for module in modules}


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `robotd bench`."""
    bench = subparsers.add_parser("bench", help="run the benchmarks (all, or the ones named)")
    bench.add_argument("names", nargs="*", help="benchmarks to run (default: all); --list shows them")
    bench.add_argument("--list", action="store_true", help="list the benchmarks and exit")
    bench.add_argument("--quick", action="store_true", help="small workloads: a smoke test, not a measurement")
    bench.add_argument("--json", metavar="PATH", help="also write every figure to this JSON file")
    bench.add_argument(
        "--report", metavar="PATH", help="also write what each benchmark printed as Markdown (docs/bench.md)"
    )
    bench.set_defaults(handler=run_benchmarks)


def run_benchmarks(args: argparse.Namespace) -> int:
    """Run the selected benchmarks and print their figures."""
    modules = _modules()
    if args.list:
        for name, module in modules.items():
            print(f"{name:12s} {(module.__doc__ or '').strip().splitlines()[0]}")
        return 0
    unknown = [name for name in args.names if name not in modules]
    if unknown:
        print(
            f"robotd bench: unknown benchmark {', '.join(unknown)}; known: {', '.join(modules)}",
            file=sys.stderr,
        )
        return 2
    figures: dict[str, dict[str, float]] = {}
    printed: dict[str, str] = {}
    for name in args.names or list(modules):
        print(f"== {name}", flush=True)
        capture = _Tee(sys.stdout)
        with contextlib.redirect_stdout(capture):
            figures[name] = modules[name].run(quick=args.quick)
            for addition in BENCHMARK_ADDITIONS.get(name, ()):
                figures[name] |= importlib.import_module(addition).run(quick=args.quick)
        printed[name] = capture.text()
    if args.report:
        with open(args.report, "w", encoding="utf-8") as out:
            out.write(_report(printed, modules, quick=args.quick))
    if args.json:
        with open(args.json, "w", encoding="utf-8") as out:
            json.dump(figures, out, indent=2)
    return 0
