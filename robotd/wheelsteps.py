"""Wheel samples into prediction steps: which samples end a step, and the body twist of the ticks between two samples.

Ticks are exact displacements: a step's twist is the wheels' mean angular speed over it through the forward
kinematics (paper eq. 1). The same arithmetic serves one step (floats) and a whole log's steps (numpy arrays).
"""

from __future__ import annotations

import bisect
import math
from typing import Any, NamedTuple

import numpy as np
import numpy.typing as npt

from robotd import kinematics
from robotd.track import StepTwists

Ticks = tuple[int, int, int, int]
PERIOD_SLACK_S = 1e-6
"""A period has passed when it is within this of passing: times far from zero (Unix time in a log) carry rounding
of a fraction of a microsecond, which must not move a step from one sample to the next."""
FloatArray = npt.NDArray[np.float64]


class Loaded(NamedTuple):
    """A log's wheel samples as loaded by the estimator: times, cumulative ticks (n x 4), the samples ending steps."""

    times: FloatArray
    ticks: npt.NDArray[np.int64]
    ends: npt.NDArray[np.int64]


def step_ends(times: list[float], period: float) -> list[int]:
    """Indices of the samples that end a step: the first sample starts the clock (index 0), then a sample ends a step
    once `period` has passed since the previous end (as fed one by one: Estimator.on_wheels)."""
    ends = [0]
    base_t = times[0] if times else 0.0
    for i in range(1, len(times)):
        t = times[i]
        if t - base_t >= period - PERIOD_SLACK_S:
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


class WheelFeed:
    """Cumulative tick samples into prediction steps: fed one at a time, or a whole log's loaded at once.

    One at a time, ticks accumulate until `period` has passed since the sample that ended the last step; the step's
    twist is their mean. Loaded, the same steps are found in one pass (step_ends) with their twists in numpy, and
    feeding only says how many samples have arrived. Either way, the twist beyond the newest step is the mean of the
    samples since it (pending).
    """

    def __init__(self, kinematics: TickKinematics, period: float) -> None:
        self.kinematics = kinematics
        self.period = period
        self.base: Ticks | None = None  # the sample that ended the last step, and the newest sample
        self.base_t = -math.inf
        self.last: Ticks | None = None
        self.last_t = -math.inf
        # loaded: the arrays, and as lists the times, the samples that end each step and each wheel's ticks
        self.loaded: Loaded | None = None
        self._times: list[float] = []
        self._ends: list[int] = []
        self.fed = 0  # loaded samples fed so far

    def accepts(self, t: float) -> bool:
        """Whether a sample at t would be taken (finite, and later than the newest)."""
        return math.isfinite(t) and t > self.last_t

    def sample(self, t: float, ticks: Ticks) -> tuple[float, tuple[float, float, float]] | None:
        """Take a sample (accepts(t) must hold); returns the step it ends, (t, twist), if it ends one.

        The first sample ends the zero-length step that starts the clock, at rest.
        """
        self.last, self.last_t = ticks, t
        if self.base is None:
            self.base, self.base_t = ticks, t
            return t, (0.0, 0.0, 0.0)
        if t - self.base_t < self.period - PERIOD_SLACK_S:
            return None
        twist = self.kinematics.twist(self.base, ticks, t - self.base_t)
        self.base, self.base_t = ticks, t
        return t, twist

    def load(
        self, times: npt.NDArray[np.float64], ticks: npt.NDArray[np.int64], ends: list[int] | None = None
    ) -> StepTwists | None:
        """Take a whole log's samples (times strictly increasing and finite, ticks n x 4, at least two): the steps
        feeding them one by one would make, after the first sample's clock start; None (nothing taken) otherwise.

        `ends`, if given, is step_ends(times, period), already computed by the caller.
        """
        if not self._can_load(times):
            return None
        self._times = times.tolist()
        self._ends = ends if ends is not None else step_ends(self._times, self.period)
        self.loaded = Loaded(times, ticks, np.array(self._ends, dtype=np.int64))
        end, begin = self.loaded.ends[1:], self.loaded.ends[:-1]
        vx, vy, wz = self.kinematics.twists(ticks[end] - ticks[begin], times[end] - times[begin])
        return StepTwists(times[end], vx, vy, wz, (vx, vy, wz))

    def load_steps(self, times: npt.NDArray[np.float64]) -> bool:
        """Take a whole log's samples that each end a step (twist samples: times strictly increasing and finite, at
        least two); False (nothing taken) otherwise. Nothing is pending between them."""
        if not self._can_load(times):
            return False
        self._times = times.tolist()
        self._ends = list(range(len(times)))
        self.loaded = Loaded(times, np.zeros((len(times), 4), dtype=np.int64), np.arange(len(times), dtype=np.int64))
        return True

    def _can_load(self, times: npt.NDArray[np.float64]) -> bool:
        """Nothing taken yet, and at least two times, all finite and strictly increasing."""
        if self.loaded is not None or self.base is not None or len(times) < 2:
            return False
        return bool(np.all(np.isfinite(times)) and np.all(np.diff(times) > 0.0))

    def feed(self, start: int, stop: int) -> int:
        """Loaded samples [start, stop) have arrived (in order); returns how many steps they complete (with the
        clock's)."""
        if start != self.fed:
            raise ValueError(f"loaded wheel samples must be fed in order: expected {self.fed}, got {start}")
        self.fed = stop
        if stop:
            self.last_t = self._times[stop - 1]
        return bisect.bisect_left(self._ends, stop)

    def pending(self, steps: int) -> tuple[float, float, float] | None:
        """The mean twist of the samples since the newest of `steps` steps (None when there are none)."""
        if self.loaded is None:
            base, last = self.base, self.last
            if base is None or last is None or self.last_t <= self.base_t:
                return None
            return self.kinematics.twist(base, last, self.last_t - self.base_t)
        newest = self.fed - 1
        if not steps or newest <= self._ends[steps - 1]:
            return None
        e = self._ends[steps - 1]
        (a1, a2, a3, a4), (b1, b2, b3, b4) = self.loaded.ticks[[e, newest]].tolist()
        return self.kinematics.twist((a1, a2, a3, a4), (b1, b2, b3, b4), self._times[newest] - self._times[e])


__all__ = ["PERIOD_SLACK_S", "Loaded", "TickKinematics", "Ticks", "WheelFeed", "step_ends"]
