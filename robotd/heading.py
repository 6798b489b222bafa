"""Heading alignment: the odometry track of a window of travel, rotated onto the IPS fixes taken along it.

The filter's heading is only observable through motion. This module keeps, per window of `window_m` of travel, the
odometry-only track (integrated from the window's start, in that start's frame) and the fixes seen along it, and fits
the rotation that lays one onto the other (least squares, outliers trimmed). The estimator compares that rotation
with its own heading and takes it when they disagree. Pure: no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

LN4 = 2.0 * math.log(2.0)  # median of a chi-square with 2 dof: |nu|^2 / sigma^2 has this median
MAX_POINTS = 400  # a robot standing still must not grow a window forever


@dataclass(slots=True)
class AlignPoint:
    """A fix (zx, zy) and the odometry-only beacon position (ox, oy) at its measurement time, in the window's frame."""

    t: float
    zx: float
    zy: float
    ox: float
    oy: float


@dataclass(frozen=True, slots=True)
class RotationFit:
    """The rotation of the odometry window onto the fixes, its std, the translation, and the window's odometry pose."""

    rotation: float
    sigma: float
    tx: float
    ty: float
    window_odo: tuple[float, float, float]


class HeadingAligner:
    """The current window's odometry track and fixes; fits their rotation once enough travel was seen."""

    def __init__(self, window_m: float, offset: tuple[float, float], *, enabled: bool) -> None:
        self.window_m = window_m
        self.offset = offset
        self.points: list[AlignPoint] | None = [] if enabled else None
        self.odo = (0.0, 0.0, 0.0)  # odometry-only pose since the window started
        self.dist = 0.0
        self.last_window_odo = (0.0, 0.0, 0.0)

    def restart(self) -> None:
        """Start a new window here (after a full window, a recovery or a re-alignment)."""
        if self.points is not None:
            self.last_window_odo = self.odo
            self.points = []
            self.odo = (0.0, 0.0, 0.0)
            self.dist = 0.0

    def track(self, u: tuple[float, float, float], dt: float) -> None:
        """Integrate the odometry-only pose over one input step of twist u (midpoint heading)."""
        if self.points is None or dt <= 0.0:
            return
        ax, ay, ath = self.odo
        th = ath + 0.5 * u[2] * dt
        c, s = math.cos(th), math.sin(th)
        self.odo = (ax + (u[0] * c - u[1] * s) * dt, ay + (u[0] * s + u[1] * c) * dt, ath + u[2] * dt)
        self.dist += math.hypot(u[0], u[1]) * dt

    def record(self, t_meas: float, zx: float, zy: float) -> None:
        """Pair a fix with the odometry-only beacon position now."""
        points = self.points
        if points is None:
            return
        ax, ay, ath = self.odo
        ox, oy = self.offset
        c, s = math.cos(ath), math.sin(ath)
        points.append(AlignPoint(t_meas, zx, zy, ax + ox * c - oy * s, ay + ox * s + oy * c))
        if len(points) > MAX_POINTS:
            del points[: MAX_POINTS // 2]

    def check(self, r: float) -> RotationFit | None:
        """The window's rotation fit once it has 40 % of its travel (None before, or when untrustworthy).

        A window that reached its full length is closed (a new one starts), so that a heading gone wrong at any time
        (unknown at start, a robot turned while carried, slip the model did not expect) is caught within one window.
        """
        points = self.points
        if points is None or len(points) < 6 or self.dist < 0.4 * self.window_m:
            return None
        fit = fit_rotation(points, 4.0 * math.sqrt(r))
        if self.dist >= self.window_m:
            self.restart()
        if fit is None:
            return None
        rotation, sigma, tx, ty = fit
        return RotationFit(rotation, sigma, tx, ty, self.odo if self.points is points else self.last_window_odo)


def fit_rotation(points: list[AlignPoint], tolerance: float) -> tuple[float, float, float, float] | None:
    """The rotation (and translation) taking odometry track onto fixes, least squares with outliers trimmed.

    Returns (rotation, its standard deviation, tx, ty) or None when the track is too short or too inconsistent.
    """
    use = points
    for _ in range(3):
        n = len(use)
        if n < 5:
            return None
        zxs, zys = [p.zx for p in use], [p.zy for p in use]
        oxs, oys = [p.ox for p in use], [p.oy for p in use]
        mzx, mzy, mox, moy = sum(zxs) / n, sum(zys) / n, sum(oxs) / n, sum(oys) / n
        dot = cross = spread = 0.0
        for pox, poy, pzx, pzy in zip(oxs, oys, zxs, zys, strict=True):
            ox, oy, zx, zy = pox - mox, poy - moy, pzx - mzx, pzy - mzy
            dot += ox * zx + oy * zy
            cross += ox * zy - oy * zx
            spread += ox * ox + oy * oy
        rotation = math.atan2(cross, dot)
        c, s = math.cos(rotation), math.sin(rotation)
        tx, ty = mzx - (mox * c - moy * s), mzy - (mox * s + moy * c)
        residuals = [
            math.hypot(pzx - (tx + pox * c - poy * s), pzy - (ty + pox * s + poy * c))
            for pox, poy, pzx, pzy in zip(oxs, oys, zxs, zys, strict=True)
        ]
        median = sorted(residuals)[len(residuals) // 2]
        bound = max(3.0 * median, tolerance)
        keep = [p for p, e in zip(use, residuals, strict=True) if e <= bound]
        if len(keep) == len(use):
            break
        use = keep
    if len(use) < 0.7 * len(points):  # too many points off the fit: no trustworthy rotation in this window
        return None
    if spread <= 0.0:
        return None
    noise = max(median / math.sqrt(LN4), 1e-3)
    sigma = noise / math.sqrt(spread)
    if sigma > 0.5:
        return None
    return rotation, sigma, tx, ty


__all__ = ["LN4", "AlignPoint", "HeadingAligner", "RotationFit", "fit_rotation"]
