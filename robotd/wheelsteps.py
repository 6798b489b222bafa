"""Wheel samples into prediction steps: which samples end a step, and the body twist of the ticks between two samples.

Ticks are exact displacements: a step's twist is the wheels' mean angular speed over it through the forward
kinematics (paper eq. 1). The same arithmetic serves one step (floats) and a whole log's steps (numpy arrays).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import numpy.typing as npt

from robotd import kinematics

Ticks = tuple[int, int, int, int]


def step_ends(times: list[float], period: float) -> list[int]:
    """Indices of the samples that end a step: the first sample starts the clock (index 0), then a sample ends a step
    once `period` has passed since the previous end (as fed one by one: Estimator.on_wheels)."""
    ends = [0]
    base_t = times[0] if times else 0.0
    for i in range(1, len(times)):
        t = times[i]
        if t - base_t >= period:
            ends.append(i)
            base_t = t
    return ends


class TickKinematics:
    """Ticks over an interval to the body twist (vx, vy, wz) in m/s and rad/s (paper eq. 1, FL FR RL RR)."""

    def __init__(self, geometry: kinematics.Geometry, counts_per_rev: int) -> None:
        self.radians_per_count = 2.0 * math.pi / counts_per_rev
        self._r4 = geometry.wheel_radius_m / 4.0
        self._r4k = geometry.wheel_radius_m / (4.0 * (geometry.lx_m + geometry.ly_m))

    def twist(self, start: Ticks, end: Ticks, dt: float) -> tuple[float, float, float]:
        """The mean twist of the ticks from `start` to `end` over dt > 0 seconds."""
        k = self.radians_per_count / dt
        twist: tuple[float, float, float] = self._forward(
            (end[0] - start[0]) * k, (end[1] - start[1]) * k, (end[2] - start[2]) * k, (end[3] - start[3]) * k
        )
        return twist

    def twists(
        self, counts: npt.NDArray[np.int64], dt: npt.NDArray[np.float64]
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """twist() of many intervals: counts (n x 4) turned over dt (n)."""
        k = self.radians_per_count / dt
        w = counts.astype(np.float64)
        result: tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64]] = self._forward(
            w[:, 0] * k, w[:, 1] * k, w[:, 2] * k, w[:, 3] * k
        )
        return result

    def _forward(self, w1: Any, w2: Any, w3: Any, w4: Any) -> Any:
        # kinematics.forward (eq. 1) on floats or arrays
        return self._r4 * (w1 + w2 + w3 + w4), self._r4 * (-w1 + w2 + w3 - w4), self._r4k * (-w1 + w2 - w3 + w4)


__all__ = ["TickKinematics", "Ticks", "step_ends"]
