"""`robotd bench`: performance figures, each as a ratio against its named baseline."""

from __future__ import annotations

import argparse
import importlib
import json
import sys
from types import ModuleType

from robotd.bench import BENCHMARK_MODULES


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
    for name in args.names or list(modules):
        print(f"== {name}", flush=True)
        figures[name] = modules[name].run(quick=args.quick)
    if args.json:
        with open(args.json, "w", encoding="utf-8") as out:
            json.dump(figures, out, indent=2)
    return 0
