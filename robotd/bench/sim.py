"""Offline simulation speed: `robotd simulate square --loops 3` against real time (target: 100x faster)."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from robotd.config.model import load
from robotd.sim.offline import simulate

NAME = "simulate"
TARGET_SPEED_UP = 100.0
CONFIG = Path(__file__).resolve().parents[2] / "config" / "sim.yaml"


def run(quick: bool) -> dict[str, float]:
    """Time the paper's square written to a file, as the command does; best of a few runs."""
    config = load(CONFIG)
    loops, repeats = (1, 1) if quick else (3, 3)
    best = float("inf")
    simulated = 0.0
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(repeats):
            started = time.perf_counter()
            with open(Path(tmp) / "square.jsonl", "w", encoding="utf-8") as out:
                summary = simulate(config, "square", config.sim.seed, loops, out)
            best = min(best, time.perf_counter() - started)
            simulated = summary.simulated_s
    speed_up = simulated / best
    verdict = "meets" if speed_up >= TARGET_SPEED_UP else "MISSES"
    print(
        f"simulate square --loops {loops}: {simulated:.1f} s simulated in {best:.3f} s (best of {repeats}) = "
        f"{speed_up:.0f}x real time; baseline real time (1x), target {TARGET_SPEED_UP:.0f}x: {verdict}"
    )
    return {"simulated_s": simulated, "wall_s": best, "speed_up_vs_real_time": speed_up}
