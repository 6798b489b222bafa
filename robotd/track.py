"""The odometry track: prediction steps in the odometry frame, and the sums that carry a state across any run of them.

Theory of operation
- Each prediction step k moves the robot over (t[k-1], t[k]] with the body twist (vx, vy, wz)[k]. Integrated from
  (0, 0, 0) at the first step, the steps give the odometry-only pose (ox, oy, oth)[k]: the odometry frame.
- The EKF's prediction is equivariant under a rigid motion of the plane: a state whose heading differs from the
  odometry's by d moves, over the same steps, by the odometry's displacement rotated by d, and its covariance grows
  by the odometry frame's growth rotated by d (F and Q are G M G^T with G a rotation: robotd.ekf). So the state at
  step j follows from the state at step b in O(1), whatever j - b:
      x_j = x_b + R(d) (o_j - o_b),   theta_j = theta_b + (oth_j - oth_b),   P_j = T (Phi P' Phi^T + Qacc) T^T
  with P' the covariance turned into the odometry frame, Phi = I + (a, b) in the theta column, (a, b) the
  perpendicular of o_j - o_b (the steps' F matrices compose by adding their columns), and
      Qacc = sum over k in (b, j] of Phi_k Q_k Phi_k^T,   Phi_k = I + perp(o_j - o_k) in the theta column,
  which expands into prefix sums of qtt_k, qtt_k w_k and qtt_k w_k w_k^T (w_k = perp(o_k)) and of Q_k's
  position block. With the heading unknown (robotd.history) the position variance also grows by q_k in every
  direction and keeps no correlation with the heading; its own prefix sums serve that mode.
- Rounding: the sums are differences of running totals over the whole track. Their error is about 1e-16 of
  (heading variance added since the start) x (distance from the odometry origin)^2: below 1e-10 m^2 after a
  kilometre of driving 100 m from the origin. A track that is trimmed (`drop_before`) restarts its totals.
Columns are Python lists (a float from a list is read several times faster than from an array); `extend` fills them
with numpy, one call for any number of steps, so that one step and a whole log's steps are the same arithmetic.
"""

from __future__ import annotations

import bisect
import math
from types import ModuleType
from typing import Any

import numpy as np
import numpy.typing as npt

from robotd import ekf

UNKNOWN_HEADING_CORRELATION_S = 0.1  # how long a velocity error from an unknown heading persists: a fix interval

FloatArray = npt.NDArray[np.float64]
State = tuple[float, float, float, ekf.Cov]
"""x, y, theta and P (upper triangle)."""

# The running totals, in this order (see the module docstring): with the heading known, qtt, qtt w, qtt w w^T and
# Q's position block; with it unknown, a^2, ab, b^2 (the steps' Phi columns), the same times the qtt total before
# the step, and the isotropic growth q.
SUMS = (
    "c",
    "s1x",
    "s1y",
    "s2xx",
    "s2xy",
    "s2yy",
    "qxx",
    "qxy",
    "qyy",
    "a2",
    "ab",
    "b2",
    "a2c",
    "abc",
    "b2c",
    "qiso",
)


class OdometryTrack:
    """Prediction steps in time order, the odometry-only pose after each, and the running totals of their noise.

    Step 0 is the clock's start (no motion). Index k of the lists is step `first + k`: trimming keeps step numbers.
    """

    def __init__(self, noise: ekf.ControlNoise, *, midpoint: bool) -> None:
        self.noise = noise
        self.midpoint = midpoint
        self.first = 0  # step number of index 0
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
        # per step, the running totals of SUMS in that order (an array when a whole log's steps came at once)
        self.sums: list[list[float]] | FloatArray = []

    def __len__(self) -> int:
        return len(self.t)

    def start(self, t: float, held: tuple[float, float, float]) -> None:
        """Start the clock at t (step 0: no motion), with the twist held after it."""
        self.first = 0
        for column in (self.t, self.vx, self.vy, self.wz, self.hx, self.hy, self.hw, self.ox, self.oy, self.oth):
            column.clear()
        self.dist.clear()
        self.t.append(t)
        for column in (self.vx, self.vy, self.wz, self.ox, self.oy, self.oth):
            column.append(0.0)
        self.hx.append(held[0])
        self.hy.append(held[1])
        self.hw.append(held[2])
        self.dist.append(0.0)
        self.sums = [[0.0] * len(SUMS)]

    def hold(self, held: tuple[float, float, float]) -> None:
        """Change the twist held after the newest step (a twist sample at its time)."""
        self.hx[-1], self.hy[-1], self.hw[-1] = held

    def append(self, t: float, u: tuple[float, float, float], held: tuple[float, float, float]) -> None:
        """Add one step ending at t (after the newest) with twist u, and `held` in force after it: extend's
        arithmetic on floats (a daemon adds its steps one at a time; numpy's per-call cost would be most of it)."""
        vx, vy, wz = u
        dt = t - self.t[-1]
        heading = self.oth[-1]
        dx, dy, c, s = displacement(vx, vy, wz, dt, heading, midpoint=self.midpoint, lib=math)
        ox, oy = self.ox[-1] + dx, self.oy[-1] + dy
        qxx, qxy, qyy, qtt = ekf.process_noise_terms(vx, vy, wz, dt, (c, s), self.noise, lib=math)
        previous = self.sums[-1]
        previous = previous.tolist() if isinstance(previous, np.ndarray) else previous
        increments = _increments(qxx, qxy, qyy, qtt, (-dy, dx), (-oy, ox), previous[0], (vx, vy, dt))
        listed: list[list[float]] = self.sums.tolist() if isinstance(self.sums, np.ndarray) else self.sums
        listed.append([total + step for total, step in zip(previous, increments, strict=True)])
        self.sums = listed
        self.t.append(t)
        self.vx.append(vx)
        self.vy.append(vy)
        self.wz.append(wz)
        self.hx.append(held[0])
        self.hy.append(held[1])
        self.hw.append(held[2])
        self.ox.append(ox)
        self.oy.append(oy)
        self.oth.append(heading + wz * dt)
        self.dist.append(self.dist[-1] + math.hypot(vx, vy) * dt)

    def drop_before(self, step: int) -> None:
        """Forget the steps before step number `step` (they can no longer be propagated from)."""
        cut = step - self.first
        if cut <= 0:
            return
        for column in (self.t, self.vx, self.vy, self.wz, self.hx, self.hy, self.hw, self.ox, self.oy, self.oth):
            del column[:cut]
        del self.dist[:cut]
        self.sums = self.sums[cut:]
        self.first = step

    def twist_at(self, t: float, visible: int) -> tuple[float, float, float] | None:
        """The twist in force at t among the first `visible` steps (that of the step containing it); None past them."""
        i = bisect.bisect_left(self.t, t, 0, visible)
        if i >= visible:
            return None
        if i == 0:
            return self.hx[0], self.hy[0], self.hw[0]
        return self.vx[i], self.vy[i], self.wz[i]

    def pose_at(self, t: float, visible: int) -> tuple[float, float, float] | None:
        """The odometry pose at t (linear between the first `visible` steps, the newest past them); None before."""
        if not visible or t < self.t[0]:
            return None
        i = bisect.bisect_right(self.t, t, 0, visible)
        ox, oy, oth = self.ox, self.oy, self.oth
        if i >= visible:
            return ox[visible - 1], oy[visible - 1], oth[visible - 1]
        t0, t1 = self.t[i - 1], self.t[i]
        f = (t - t0) / (t1 - t0)
        return (
            ox[i - 1] + f * (ox[i] - ox[i - 1]),
            oy[i - 1] + f * (oy[i] - oy[i - 1]),
            oth[i - 1] + f * (oth[i] - oth[i - 1]),
        )

    def newest(self, visible: int, clock: float) -> tuple[float, tuple[float, float, float], float]:
        """Time, odometry pose and distance travelled at the newest of `visible` steps (the clock's start, at rest,
        before any)."""
        if not visible:
            return clock, (0.0, 0.0, 0.0), 0.0
        k = visible - 1
        return self.t[k], (self.ox[k], self.oy[k], self.oth[k]), self.dist[k]

    def across(self, b: int, j: int, state: State, *, heading_known: bool) -> State:
        """The state at step j (list index) from the state at step b <= j, in O(1) (see the module docstring).

        With the heading unknown the state's heading correlations (xt, yt) must be zero, as every step leaves them.
        """
        if j == b:
            return state
        ox, oy, oth = self.ox, self.oy, self.oth
        carried: State = carry(
            state,
            oth[b],
            (ox[j] - ox[b], oy[j] - oy[b], oth[j] - oth[b]),
            (-oy[j], ox[j]),
            *self._totals(b, j),
            heading_known=heading_known,
            lib=math,
        )
        return carried

    def _totals(self, b: int, j: int) -> tuple[list[float], list[float]]:
        """The running totals at steps b and j, as floats (an array's elements would make the arithmetic numpy's)."""
        sums = self.sums
        if isinstance(sums, np.ndarray):  # once: rows read one by one are faster from lists
            sums = self.sums = sums.tolist()
        return sums[b], sums[j]

def displacement(vx: Any, vy: Any, wz: Any, dt: Any, heading: Any, *, midpoint: bool, lib: ModuleType) -> Any:
    """A step's displacement (dx, dy) in the odometry frame from `heading` before it, and the cos and sin used (eq. 5
    at the midpoint heading, or the paper's start heading): floats with lib=math, arrays with numpy."""
    th = heading + 0.5 * wz * dt if midpoint else heading
    c, s = lib.cos(th), lib.sin(th)
    return (vx * c - vy * s) * dt, (vx * s + vy * c) * dt, c, s


def _increments(  # noqa: PLR0917 - a step's parts, as floats or arrays
    qxx: Any, qxy: Any, qyy: Any, qtt: Any, column: tuple[Any, Any], w: tuple[Any, Any], before: Any, move: Any
) -> list[Any]:
    """What a step adds to each running total, in SUMS order: `column` is its Phi column (a, b), w the perpendicular
    of the odometry position after it, `before` the qtt total before it, move its (vx, vy, dt)."""
    a, b = column
    wx, wy = w
    return [
        qtt,
        qtt * wx,
        qtt * wy,
        qtt * wx * wx,
        qtt * wx * wy,
        qtt * wy * wy,
        qxx,
        qxy,
        qyy,
        a * a,
        a * b,
        b * b,
        a * a * before,
        a * b * before,
        b * b * before,
        unknown_heading_variance(*move),
    ]


def unknown_heading_variance(vx: Any, vy: Any, dt: Any) -> Any:
    """The position variance (per axis) a step of (vx, vy) for dt adds when the heading is unknown: a velocity
    error of up to twice the speed, correlated over UNKNOWN_HEADING_CORRELATION_S, about one fix interval (each fix
    re-anchors the position, so only the motion since the last one is in doubt), as white noise of that density."""
    return 4.0 * (vx * vx + vy * vy) * dt * UNKNOWN_HEADING_CORRELATION_S


def carry(  # noqa: PLR0917 - the closed form's inputs, as plain floats (or arrays of them)
    state: Any,
    oth_b: Any,
    moved: tuple[Any, Any, Any],
    w_j: tuple[Any, Any],
    sums_b: Any,
    sums_j: Any,
    *,
    heading_known: bool,
    lib: ModuleType,
) -> Any:
    """The state at step j from the state at step b: `moved` is the odometry's (dx, dy, dtheta) from b to j, w_j
    the perpendicular of the odometry position at j, sums_b and sums_j the running totals at b and j (SUMS order).

    Floats with lib=math; arrays (one state per element) with lib=numpy: the same arithmetic.
    """
    x, y, th, p = state
    dx, dy, dth = moved
    d = th - oth_b
    c, s = lib.cos(d), lib.sin(d)
    x_new, y_new = x + c * dx - s * dy, y + s * dx + c * dy
    th_new = ekf.wrap_angle(th + dth)
    xx, xy, xt, yy, yt, tt = p
    cs, c2, s2 = c * s, c * c, s * s
    # P' = R^T P R: the covariance in the odometry frame
    pxx = c2 * xx + 2.0 * cs * xy + s2 * yy
    pxy = cs * (yy - xx) + (c2 - s2) * xy
    pyy = s2 * xx - 2.0 * cs * xy + c2 * yy
    pxt, pyt = c * xt + s * yt, c * yt - s * xt
    c0, s1x0, s1y0, s2xx0, s2xy0, s2yy0, qxx0, qxy0, qyy0, a20, ab0, b20, a2c0, abc0, b2c0, qiso0 = sums_b
    c1, s1x1, s1y1, s2xx1, s2xy1, s2yy1, qxx1, qxy1, qyy1, a21, ab1, b21, a2c1, abc1, b2c1, qiso1 = sums_j
    s0 = c1 - c0
    sqxx, sqxy, sqyy = qxx1 - qxx0, qxy1 - qxy0, qyy1 - qyy0
    if heading_known:
        a, bb = -dy, dx
        wx, wy = w_j
        s1x, s1y = s1x1 - s1x0, s1y1 - s1y0
        s2xx, s2xy, s2yy = s2xx1 - s2xx0, s2xy1 - s2xy0, s2yy1 - s2yy0
        nxx = pxx + 2.0 * a * pxt + a * a * tt + sqxx + s0 * wx * wx - 2.0 * wx * s1x + s2xx
        nxy = pxy + a * pyt + bb * pxt + a * bb * tt + sqxy + s0 * wx * wy - wx * s1y - wy * s1x + s2xy
        nyy = pyy + 2.0 * bb * pyt + bb * bb * tt + sqyy + s0 * wy * wy - 2.0 * wy * s1y + s2yy
        nxt = pxt + a * tt + s0 * wx - s1x
        nyt = pyt + bb * tt + s0 * wy - s1y
    else:
        k0 = tt - c0  # tt before step k is k0 + (c total before step k)
        qiso = qiso1 - qiso0
        nxx = pxx + k0 * (a21 - a20) + (a2c1 - a2c0) + sqxx + qiso
        nxy = pxy + k0 * (ab1 - ab0) + (abc1 - abc0) + sqxy
        nyy = pyy + k0 * (b21 - b20) + (b2c1 - b2c0) + sqyy + qiso
        nxt = nyt = 0.0 * tt
    # back to the state's frame: P = R P'' R^T
    p_new = (
        c2 * nxx - 2.0 * cs * nxy + s2 * nyy,
        cs * (nxx - nyy) + (c2 - s2) * nxy,
        c * nxt - s * nyt,
        s2 * nxx + 2.0 * cs * nxy + c2 * nyy,
        s * nxt + c * nyt,
        tt + s0,
    )
    return x_new, y_new, th_new, p_new


__all__ = [
    "SUMS",
    "UNKNOWN_HEADING_CORRELATION_S",
    "OdometryTrack",
    "State",
    "carry",
    "displacement",
    "unknown_heading_variance",
]
