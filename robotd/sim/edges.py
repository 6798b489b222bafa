"""Wheel angles to encoder edges: the count after each edge and the microsecond tick at which it happens (numpy).

An encoder with c counts per turn has an edge wherever the wheel's angle crosses a multiple of 2 pi / c; the count
at angle a is floor(a c / 2 pi), as `Robot.encoder_counts` says. Over one physics step the angle moves from a0 to
a1; the edges in between are placed by linear interpolation of the angle over the step (the wheel's speed barely
changes within a few milliseconds). A wheel that reverses inside a step emits only the net edges of the step.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

Int64Array = npt.NDArray[np.int64]


def wheel_edges(
    angle0: float, angle1: float, tick0_us: int, tick1_us: int, counts_per_rev: int
) -> tuple[Int64Array, Int64Array]:
    """The (ticks, counts) of every edge while the angle goes from angle0 at tick0 to angle1 at tick1.

    `counts[i]` is the cumulative count (forward positive) after the edge at `ticks[i]`; ticks are non-decreasing
    integers in [tick0_us, tick1_us].
    """
    scale = counts_per_rev / (2.0 * math.pi)
    start, end = angle0 * scale, angle1 * scale
    count0, count1 = math.floor(start), math.floor(end)
    if count0 == count1 or start == end:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty
    if count1 > count0:  # forward: the count becomes p when the scaled angle rises through p
        counts = np.arange(count0 + 1, count1 + 1, dtype=np.int64)
        crossings = counts.astype(np.float64)
    else:  # backward: the count becomes p when the scaled angle falls through p + 1
        counts = np.arange(count0 - 1, count1 - 1, -1, dtype=np.int64)
        crossings = (counts + 1).astype(np.float64)
    fraction = (crossings - start) / (end - start)
    ticks = tick0_us + np.floor(fraction * (tick1_us - tick0_us)).astype(np.int64)
    return np.clip(ticks, tick0_us, tick1_us), counts
