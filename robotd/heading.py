"""Heading alignment: the odometry track of a window of travel, rotated onto the IPS fixes taken along it.

The filter's heading is only observable through motion. This module keeps, per window of `window_m` of travel, the
odometry-only track (integrated from the window's start, in that start's frame) and the fixes seen along it, and fits
the rotation that lays one onto the other (least squares, outliers trimmed). The estimator compares that rotation
with its own heading and takes it when they disagree. Pure: no I/O.
"""

from __future__ import annotations

import math
from collections import deque
from typing import NamedTuple

LN4 = 2.0 * math.log(2.0)  # median of a chi-square with 2 dof: |nu|^2 / sigma^2 has this median
MAX_POINTS = 400  # a robot standing still must not grow a window forever
TRAIL_S = 5.0  # how far back odometry poses are kept to pair a late fix with where the robot was when measured


class RotationFit(NamedTuple):
    """The rotation of the odometry window onto the fixes, its std, the translation, and the window's odometry pose.

    A NamedTuple: as immutable as a frozen dataclass, and built several times faster (after most fixes).
    """

    rotation: float
    sigma: float
    tx: float
    ty: float
    window_odo: tuple[float, float, float]
    window: int  # which window the fit is of (successive windows have successive numbers)


class HeadingAligner:
    """The current window's odometry track and fixes; fits their rotation once enough travel was seen.

    The window's fixes (zx, zy) and the odometry-only beacon positions (ox, oy) paired with them are kept as four
    columns, in the order the fit reads them.
    """

    def __init__(self, window_m: float, offset: tuple[float, float], *, enabled: bool) -> None:
        self.window_m = window_m
        self.offset = offset
        self.enabled = enabled
        self.zxs: list[float] = []
        self.zys: list[float] = []
        self.oxs: list[float] = []
        self.oys: list[float] = []
        self.odo = (0.0, 0.0, 0.0)  # odometry-only pose since the window started
        self.dist = 0.0
        self.last_window_odo = (0.0, 0.0, 0.0)
        self.t = -math.inf  # time of self.odo
        # (t, x, y, theta) of the odometry-only pose in this window, newest last: fixes are paired by their
        # measurement time, so a late fix meets the pose the robot had when the beacon was measured
        self.trail: deque[tuple[float, float, float, float]] = deque()
        self.window = 0  # how many windows were started: tells the fits of successive windows apart

    def restart(self) -> None:
        """Start a new window here (after a full window, a recovery or a re-alignment)."""
        if self.enabled:
            self.last_window_odo = self.odo
            self.zxs, self.zys, self.oxs, self.oys = [], [], [], []
            self.odo = (0.0, 0.0, 0.0)
            self.dist = 0.0
            self.trail.clear()
            self.window += 1

    def track(self, u: tuple[float, float, float], dt: float, t: float) -> None:
        """Integrate the odometry-only pose over one input step of twist u (midpoint heading) that ends at t."""
        if not self.enabled or dt <= 0.0:
            return
        vx, vy, wz = u
        ax, ay, ath = self.odo
        trail = self.trail
        if not trail:
            trail.append((t - dt, ax, ay, ath))
        th = ath + 0.5 * wz * dt
        c, s = math.cos(th), math.sin(th)
        self.odo = (ax + (vx * c - vy * s) * dt, ay + (vx * s + vy * c) * dt, ath + wz * dt)
        self.t = t
        trail.append((t, *self.odo))
        while len(trail) > 2 and trail[1][0] < t - TRAIL_S:
            trail.popleft()
        self.dist += math.hypot(vx, vy) * dt

    def _odo_at(self, t: float) -> tuple[float, float, float] | None:
        """The odometry-only pose at time t (linear between tracked steps); None before the trail begins."""
        trail = self.trail
        if not trail or t >= trail[-1][0]:
            return self.odo
        if t < trail[0][0]:
            return None
        for k in range(len(trail) - 1, 0, -1):  # late fixes are recent: search from the newest end
            t0, x0, y0, th0 = trail[k - 1]
            if t0 <= t:
                t1, x1, y1, th1 = trail[k]
                f = (t - t0) / (t1 - t0) if t1 > t0 else 1.0
                return x0 + f * (x1 - x0), y0 + f * (y1 - y0), th0 + f * (th1 - th0)
        return None

    def record(self, zx: float, zy: float, t_meas: float) -> None:
        """Pair a fix measured at t_meas with the odometry-only beacon position then (skipped if before the window)."""
        if not self.enabled:
            return
        odo = self._odo_at(t_meas)
        if odo is None:
            return
        ax, ay, ath = odo
        ox, oy = self.offset
        c, s = math.cos(ath), math.sin(ath)
        self.zxs.append(zx)
        self.zys.append(zy)
        self.oxs.append(ax + ox * c - oy * s)
        self.oys.append(ay + ox * s + oy * c)
        if len(self.zxs) > MAX_POINTS:
            for column in (self.zxs, self.zys, self.oxs, self.oys):
                del column[: MAX_POINTS // 2]

    def check(self, r: float, *, whole: bool = False) -> RotationFit | None:
        """The window's rotation fit once it has 40 % of its travel, or all of it when `whole` (None before, or when
        untrustworthy).

        A window that reached its full length is closed (a new one starts), so that a heading gone wrong at any time
        (unknown at start, a robot turned while carried, slip the model did not expect) is caught within one window.
        """
        if not self.enabled or len(self.zxs) < 6 or self.dist < (1.0 if whole else 0.4) * self.window_m:
            return None
        fit = fit_rotation(self.oxs, self.oys, self.zxs, self.zys, 4.0 * math.sqrt(r))
        odo, window = self.odo, self.window
        if self.dist >= self.window_m:
            self.restart()
        if fit is None:
            return None
        rotation, sigma, tx, ty = fit
        return RotationFit(rotation, sigma, tx, ty, odo, window)


def fit_rotation(
    oxs: list[float], oys: list[float], zxs: list[float], zys: list[float], tolerance: float
) -> tuple[float, float, float, float] | None:
    """The rotation (and translation) taking the odometry track (oxs, oys) onto the fixes (zxs, zys), least squares
    with outliers trimmed.

    Returns (rotation, its standard deviation, tx, ty) or None when the track is too short or too inconsistent.
    """
    count = len(oxs)
    cos, sin, hypot = math.cos, math.sin, math.hypot
    for _ in range(3):
        n = len(oxs)
        if n < 5:
            return None
        mzx, mzy, mox, moy = sum(zxs) / n, sum(zys) / n, sum(oxs) / n, sum(oys) / n
        dot = cross = spread = 0.0
        for pox, poy, pzx, pzy in zip(oxs, oys, zxs, zys, strict=True):
            ox, oy, zx, zy = pox - mox, poy - moy, pzx - mzx, pzy - mzy
            dot += ox * zx + oy * zy
            cross += ox * zy - oy * zx
            spread += ox * ox + oy * oy
        rotation = math.atan2(cross, dot)
        c, s = cos(rotation), sin(rotation)
        tx, ty = mzx - (mox * c - moy * s), mzy - (mox * s + moy * c)
        residuals = [
            hypot(pzx - (tx + pox * c - poy * s), pzy - (ty + pox * s + poy * c))
            for pox, poy, pzx, pzy in zip(oxs, oys, zxs, zys, strict=True)
        ]
        median = sorted(residuals)[n // 2]
        bound = max(3.0 * median, tolerance)
        keep = [i for i, e in enumerate(residuals) if e <= bound]
        if len(keep) == n:
            break
        oxs, oys = [oxs[i] for i in keep], [oys[i] for i in keep]
        zxs, zys = [zxs[i] for i in keep], [zys[i] for i in keep]
    if len(oxs) < 0.7 * count:  # too many points off the fit: no trustworthy rotation in this window
        return None
    if spread <= 0.0:
        return None
    noise = max(median / math.sqrt(LN4), 1e-3)
    sigma = noise / math.sqrt(spread)
    if sigma > 0.5:
        return None
    return rotation, sigma, tx, ty


__all__ = ["LN4", "HeadingAligner", "RotationFit", "fit_rotation"]
