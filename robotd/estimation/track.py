"""The odometry track: the estimator's prediction steps in time order, and the odometry-only pose after each.

Each prediction step k moves the robot over (t[k-1], t[k]] with the body twist (vx, vy, wz)[k]; after it, the twist
(hx, hy, hw)[k] is in force (held until the next step: the pose beyond the newest step is extrapolated with it).
Integrated from (0, 0, 0) at the first step (eq. 5, robotd.estimation.ekf.displacement), the steps give the
odometry-only pose (ox, oy, oth)[k], the odometry frame in which heading alignment (robotd.estimation.heading) compares
the track with the fixes, and the distance travelled. Pure.
"""

from __future__ import annotations

import bisect
import math

from robotd.estimation import ekf

Twist3 = tuple[float, float, float]
"""A body twist (vx, vy, wz) in m/s and rad/s."""


class OdometryTrack:
    """Prediction steps in time order, the twist held after each, and the odometry-only pose after each.

    Step 0 is the clock's start (no motion). Steps before the ones still needed can be dropped (drop_before).
    """

    def __init__(self, *, midpoint: bool) -> None:
        self.midpoint = midpoint
        self.t: list[float] = []
        self.vx: list[float] = []
        self.vy: list[float] = []
        self.wz: list[float] = []
        self.hx: list[float] = []  # twist held after the step
        self.hy: list[float] = []
        self.hw: list[float] = []
        self.ox: list[float] = []
        self.oy: list[float] = []
        self.oth: list[float] = []  # unwrapped
        self.dist: list[float] = []  # distance travelled since the track began
        # the variance of motion the step's twist does not describe (a gap in a twist stream: see
        # robotd.estimation.estimator), per axis of position and of heading, over the whole step
        self.gap_var: list[float] = []
        self.gap_var_th: list[float] = []

    def __len__(self) -> int:
        return len(self.t)

    def start(self, t: float, held: Twist3) -> None:
        """Start the clock at t (step 0: no motion), with the twist held after it."""
        for column in self._columns():
            column.clear()
        self.t.append(t)
        for column in (self.vx, self.vy, self.wz, self.ox, self.oy, self.oth, self.dist, self.gap_var, self.gap_var_th):
            column.append(0.0)
        self.hold(held, new=True)

    def hold(self, held: Twist3, *, new: bool = False) -> None:
        """Change the twist held after the newest step (a twist sample at its time), or add it for a new step."""
        if new:
            self.hx.append(held[0])
            self.hy.append(held[1])
            self.hw.append(held[2])
        else:
            self.hx[-1], self.hy[-1], self.hw[-1] = held

    def append(self, t: float, u: Twist3, held: Twist3, gap_var: tuple[float, float] = (0.0, 0.0)) -> None:
        """Add one step ending at t (after the newest) with twist u, and `held` in force after it; gap_var: the
        variance (position per axis, heading) of the motion over the step that u does not describe."""
        vx, vy, wz = u
        dt = t - self.t[-1]
        heading = self.oth[-1]
        dx, dy, _, _ = ekf.displacement(vx, vy, wz, dt, heading, midpoint=self.midpoint)
        self.t.append(t)
        self.vx.append(vx)
        self.vy.append(vy)
        self.wz.append(wz)
        self.hold(held, new=True)
        self.ox.append(self.ox[-1] + dx)
        self.oy.append(self.oy[-1] + dy)
        self.oth.append(heading + wz * dt)
        self.dist.append(self.dist[-1] + math.hypot(vx, vy) * dt)
        self.gap_var.append(gap_var[0])
        self.gap_var_th.append(gap_var[1])

    def drop_before(self, index: int) -> None:
        """Forget the steps before list index `index` (no state will be carried from them again)."""
        if index > 0:
            for column in self._columns():
                del column[:index]

    def twist_at(self, t: float) -> Twist3 | None:
        """The twist in force at t (that of the step containing it; the first step's held twist before it); None
        past the newest step."""
        i = bisect.bisect_left(self.t, t)
        if i >= len(self.t):
            return None
        if i == 0:
            return self.hx[0], self.hy[0], self.hw[0]
        return self.vx[i], self.vy[i], self.wz[i]

    def pose_at(self, t: float) -> tuple[float, float, float] | None:
        """The odometry pose at t (linear between steps, the newest past them); None before the first step."""
        at = self._at(t, (self.ox, self.oy, self.oth))
        return None if at is None else (at[0], at[1], at[2])

    def travel_at(self, t: float) -> tuple[float, float]:
        """Distance driven and heading turned (unwrapped) since the track began, at t (linear between steps, the
        newest past them; 0 before the first step)."""
        at = self._at(t, (self.dist, self.oth))
        return (0.0, 0.0) if at is None else (at[0], at[1])

    def _at(self, t: float, columns: tuple[list[float], ...]) -> list[float] | None:
        """The columns at t, linear between steps, the newest past them; None before the first step."""
        if not self.t or t < self.t[0]:
            return None
        i = bisect.bisect_right(self.t, t)
        if i >= len(self.t):
            return [column[-1] for column in columns]
        f = (t - self.t[i - 1]) / (self.t[i] - self.t[i - 1])
        return [column[i - 1] + f * (column[i] - column[i - 1]) for column in columns]

    def newest(self, clock: float) -> tuple[float, tuple[float, float, float], float]:
        """Time, odometry pose and distance travelled at the newest step (the clock's start, at rest, before any)."""
        if not self.t:
            return clock, (0.0, 0.0, 0.0), 0.0
        return self.t[-1], (self.ox[-1], self.oy[-1], self.oth[-1]), self.dist[-1]

    def _columns(self) -> tuple[list[float], ...]:
        return (
            self.t,
            self.vx,
            self.vy,
            self.wz,
            self.hx,
            self.hy,
            self.hw,
            self.ox,
            self.oy,
            self.oth,
            self.dist,
            self.gap_var,
            self.gap_var_th,
        )


__all__ = ["OdometryTrack", "Twist3"]
