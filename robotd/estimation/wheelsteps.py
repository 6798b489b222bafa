"""Wheel samples into prediction steps: which samples end a step, and the body twist of the ticks between two samples.

Ticks are exact displacements: a step's twist is the wheels' mean angular speed over it through the forward
kinematics (paper eq. 1)."""

from __future__ import annotations

import math

from robotd import kinematics

Ticks = tuple[int, int, int, int]
PERIOD_SLACK_S = 1e-6
"""A period has passed when it is within this of passing: times far from zero (Unix time in a log) carry rounding
of a fraction of a microsecond, which must not move a step from one sample to the next."""


class TickKinematics:
    """Ticks over an interval to the body twist (vx, vy, wz) in m/s and rad/s (paper eq. 1, FL FR RL RR)."""

    def __init__(self, geometry: kinematics.Geometry, counts_per_rev: int) -> None:
        self.geometry = geometry
        self.radians_per_count = 2.0 * math.pi / counts_per_rev
        # eq. 1 is linear: its twist per count of each wheel, taken from kinematics.forward once (the per-sample path
        # then costs a few multiplications, not a Twist per call)
        c = self.radians_per_count
        one_count = ((c, 0.0, 0.0, 0.0), (0.0, c, 0.0, 0.0), (0.0, 0.0, c, 0.0), (0.0, 0.0, 0.0, c))
        per_count = [kinematics.forward(geometry, turn) for turn in one_count]
        self._vx = tuple(t.vx for t in per_count)
        self._vy = tuple(t.vy for t in per_count)
        self._wz = tuple(t.wz for t in per_count)

    def twist(self, start: Ticks, end: Ticks, dt: float) -> tuple[float, float, float]:
        """The mean twist of the ticks from `start` to `end` over dt > 0 seconds."""
        d0, d1, d2, d3 = end[0] - start[0], end[1] - start[1], end[2] - start[2], end[3] - start[3]
        vx, vy, wz = self._vx, self._vy, self._wz
        return (
            (vx[0] * d0 + vx[1] * d1 + vx[2] * d2 + vx[3] * d3) / dt,
            (vy[0] * d0 + vy[1] * d1 + vy[2] * d2 + vy[3] * d3) / dt,
            (wz[0] * d0 + wz[1] * d1 + wz[2] * d2 + wz[3] * d3) / dt,
        )


class WheelFeed:
    """Cumulative tick samples into prediction steps.

    Ticks accumulate until `period` has passed since the sample that ended the last step; the step's twist is their
    mean. The twist beyond the newest step is the mean of the samples since it (pending).
    """

    def __init__(self, kinematics: TickKinematics, period: float) -> None:
        self.kinematics = kinematics
        self.period = period
        self.base: Ticks | None = None  # the sample that ended the last step, and the newest sample
        self.base_t = -math.inf
        self.last: Ticks | None = None
        self.last_t = -math.inf

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

    def pending(self) -> tuple[float, float, float] | None:
        """The mean twist of the samples since the newest step (None when there are none)."""
        base, last = self.base, self.last
        if base is None or last is None or self.last_t <= self.base_t:
            return None
        return self.kinematics.twist(base, last, self.last_t - self.base_t)


__all__ = ["PERIOD_SLACK_S", "TickKinematics", "Ticks", "WheelFeed"]
