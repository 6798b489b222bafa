"""Benchmarks run by `robotd bench`: each compares robotd against a named baseline in one process.

Each benchmark module has `NAME`, a one-line `__doc__`, and `run(quick: bool) -> dict[str, float]`, which prints
its own lines and returns its figures (for `--json`). `quick` shrinks the workload for a smoke test.
"""

BENCHMARK_MODULES: tuple[str, ...] = (
    "robotd.bench.encoders",
    "robotd.bench.ekf",
    "robotd.bench.marvelmind",
    "robotd.bench.sim",
    "robotd.bench.daemon",
    "robotd.bench.viewer",
    "robotd.bench.fleet",
)

BENCHMARK_ADDITIONS: dict[str, tuple[str, ...]] = {
    "encoders": ("robotd.bench.gpiod",),
    "daemon": ("robotd.bench.gpiod_deadman",),
}
"""Modules whose `run(quick)` adds figures to the benchmark named by the key: run right after it, their lines printed
and their figures reported under its name (so `robotd bench encoders` shows both GPIO back-ends)."""
