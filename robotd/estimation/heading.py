"""Heading alignment: the odometry track of a window of travel, rotated onto the IPS fixes taken along it.

The filter's heading is only observable through motion. This module keeps, per window of `window_m` of travel, the
odometry-only track (integrated from the window's start, in that start's frame) and the fixes seen along it, and fits
the rotation that lays one onto the other (least squares, outliers trimmed). The estimator compares that rotation
with its own heading and takes it when they disagree. Pure: no I/O.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from robotd.estimation.ar1 import lag_one_correlation
from robotd.estimation.ekf import wrap_angle
from robotd.estimation.modes import HeadingEvidence, HeadingMode

LN4 = 2.0 * math.log(2.0)  # median of a chi-square with 2 dof: |nu|^2 / sigma^2 has this median
MAX_POINTS = 400  # a robot standing still must not grow a window forever
MIN_REALIGN_RAD = 0.35  # smaller heading errors are the EKF's own business: it corrects them from fixes in motion
MAX_FIT_SIGMA_RAD = 0.15  # a fit less certain than this decides nothing about a heading the filter already has
# a fit trims its outliers by the median residual, which needs this many points; fewer fit untrimmed (the provisional
# heading's first guide: the fixes have passed the gate, and its sigma says how little three points tell)
MIN_TRIMMED_POINTS = 5
# a robust fit's start tries rotations this far apart (5 degrees: 4 cm across at 0.5 m from a window's middle, a
# third of the 4 sigma tolerance), then refits by least squares, trimming and taking back points this many times
CONSENSUS_ANGLES = 72
MAX_TRIM_PASSES = 4
FIT_SPACING = 0.25  # of the window's travel between two fits (at 40, 65, 90 and 100 %)


class FixSpread(NamedTuple):
    """The residuals of a rotation fit: their number, noise variance per axis and lag-one correlation (0: white)."""

    residuals: int
    variance: float
    correlation: float


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
    fixes: FixSpread  # what the fit's residuals say of the fixes


class HeadingAligner:
    """The current window's fixes and the odometry-only beacon positions paired with them; fits their rotation once
    enough travel was seen.

    Odometry poses come from the estimator's odometry track (robotd.estimation.track), in its frame; the window keeps
    its start pose and turns them into the window's frame. The pairs are kept as four columns, in the order the fit
    reads them.
    """

    def __init__(self, window_m: float, offset: tuple[float, float], *, enabled: bool) -> None:
        self.window_m = window_m
        self.offset = offset
        self.enabled = enabled
        self.zxs: list[float] = []
        self.zys: list[float] = []
        self.oxs: list[float] = []
        self.oys: list[float] = []
        # the window's start: time, odometry pose and distance travelled then (the estimator starts the first window
        # when a fix places the position)
        self.start_t = 0.0
        self.start_pose = (0.0, 0.0, 0.0)
        self.start_dist = 0.0
        self.last_fit_dist = -math.inf  # travel (in the window) at the last fit: fits are spaced FIT_SPACING apart
        self.next_fit = math.inf  # no fit is due before this distance travelled (since start-up): check() may skip
        self.window = 0  # how many windows were started: tells the fits of successive windows apart
        self.moved = False  # whether the window's odometry points are not all one: a rotation fit needs a track

    def restart(self, t: float, pose: tuple[float, float, float], dist: float) -> None:
        """Start a new window at time t, where the odometry pose was `pose` after `dist` of travel."""
        if self.enabled:
            self.zxs, self.zys, self.oxs, self.oys = [], [], [], []
            self.moved = False
            self.start_t, self.start_pose, self.start_dist = t, pose, dist
            self.last_fit_dist = -math.inf
            self.next_fit = dist + 0.4 * self.window_m
            self.window += 1

    def in_window(self, pose: tuple[float, float, float]) -> tuple[float, float, float]:
        """An odometry pose in the window's frame (relative to its start)."""
        sx, sy, sth = self.start_pose
        c, s = math.cos(sth), math.sin(sth)
        dx, dy = pose[0] - sx, pose[1] - sy
        return c * dx + s * dy, c * dy - s * dx, pose[2] - sth

    def record(self, zx: float, zy: float, t_meas: float, pose: tuple[float, float, float] | None) -> None:
        """Pair a fix measured at t_meas with the odometry-only beacon position then (`pose`: the odometry pose at
        t_meas, None when unknown); skipped if measured before the window began."""
        if not self.enabled or pose is None or t_meas < self.start_t:
            return
        ax, ay, ath = self.in_window(pose)
        ox, oy = self.offset
        c, s = math.cos(ath), math.sin(ath)
        px, py = ax + ox * c - oy * s, ay + ox * s + oy * c
        if not self.moved and self.oxs:
            self.moved = px != self.oxs[0] or py != self.oys[0]
        self.zxs.append(zx)
        self.zys.append(zy)
        self.oxs.append(px)
        self.oys.append(py)
        if len(self.zxs) > MAX_POINTS:
            for column in (self.zxs, self.zys, self.oxs, self.oys):
                del column[: MAX_POINTS // 2]

    def fit_so_far(
        self, r: float, min_points: int = MIN_TRIMMED_POINTS
    ) -> tuple[float, float, float, float, FixSpread] | None:
        """trimmed_rotation_fit of the window's track onto its fixes so far (outliers beyond 4 sigma of the IPS noise
        variance r trimmed), from min_points fixes."""
        if not self.moved:
            # a track that is one point has no rotation (the fit would find none): at rest with the heading unknown
            # the estimator asks at every fix, and the window grows with every fix
            return None
        return trimmed_rotation_fit(self.oxs, self.oys, self.zxs, self.zys, 4.0 * math.sqrt(r), min_points=min_points)

    def check(
        self, r: float, now_t: float, now: tuple[float, float, float], dist: float, *, whole: bool = False
    ) -> RotationFit | None:
        """The window's rotation fit once it has 40 % of its travel, or all of it when `whole` (None before, between
        fits, or when untrustworthy); at now_t the odometry pose is `now` after `dist` of travel.

        Fits are spaced FIT_SPACING of the window's travel apart (the fixes between two fits change little). A window
        that reached its full length is closed (a new one starts), so that a heading gone wrong at any time (unknown
        at start, a robot turned while carried, slip the model did not expect) is caught within one window.
        """
        if not self.enabled:
            return None
        travelled = dist - self.start_dist
        full = travelled >= self.window_m
        if len(self.zxs) < 6 or travelled < (1.0 if whole else 0.4) * self.window_m:
            return None
        if not full and travelled - self.last_fit_dist < FIT_SPACING * self.window_m:
            return None
        self.last_fit_dist = travelled
        self.next_fit = self.start_dist + min(travelled + FIT_SPACING * self.window_m, self.window_m)
        fit = self.fit_so_far(r)
        odo, window = self.in_window(now), self.window
        if full:
            self.restart(now_t, now, dist)
        if fit is None:
            return None
        rotation, sigma, tx, ty, spread = fit
        return RotationFit(rotation, sigma, tx, ty, odo, window, spread)


class HeadingCheck:
    """What a window's rotation fit says about the filter's heading, as the evidence robotd.estimation.modes takes;
    keeps the disagreeing window that a SUSPECT heading waits on."""

    def __init__(self) -> None:
        self.suspect: tuple[int, float, float] | None = None  # (window, signed disagreement, its sigma)

    def evidence(
        self, fit: RotationFit, filter_theta: float, filter_var: float, heading: HeadingMode
    ) -> HeadingEvidence | None:
        """The fit's evidence (None: it decides nothing), given the heading mode; filter_theta and filter_var are the
        filter's heading and its variance now (at the fit's window_odo)."""
        # the filter's heading at the window's start is its current heading less the odometry turn since
        filter_start = wrap_angle(filter_theta - fit.window_odo[2])
        signed = wrap_angle(fit.rotation - filter_start)
        sigma = fit.sigma
        if heading is HeadingMode.UNKNOWN:
            # any fit is better than a heading not known at all: the filter takes it with the fit's own variance
            self.suspect = None
            return HeadingEvidence.WHOLE_WINDOW
        if sigma > MAX_FIT_SIGMA_RAD:
            return None
        spread = math.sqrt(sigma * sigma + filter_var)
        if abs(signed) <= max(4.0 * spread, MIN_REALIGN_RAD):
            if abs(signed) <= 3.0 * spread:
                self.suspect = None
                return HeadingEvidence.AGREES
            return None
        if heading is HeadingMode.ALIGNED:
            self.suspect = None
            return HeadingEvidence.DISAGREES
        suspect, window = self.suspect, fit.window
        if suspect is None:  # (CONFIRMED) one window disagrees: a suspect
            self.suspect = (window, signed, sigma)
            return HeadingEvidence.DISAGREES
        if suspect[0] == window:  # the suspect window itself, fitted again
            return None
        if abs(wrap_angle(signed - suspect[1])) > 3.0 * math.hypot(sigma, suspect[2]):
            self.suspect = (window, signed, sigma)  # two windows that disagree with each other: neither is proof
            return HeadingEvidence.DISAGREES
        self.suspect = None
        return HeadingEvidence.DISAGREES_AGAIN


def fit_rotation(oxs: list[float], oys: list[float], zxs: list[float], zys: list[float]) -> tuple[float, float, float]:
    """The rotation and translation (rotation, tx, ty) taking points (oxs, oys) onto points (zxs, zys), least
    squares (at least one point)."""
    n = len(oxs)
    mzx, mzy, mox, moy = sum(zxs) / n, sum(zys) / n, sum(oxs) / n, sum(oys) / n
    dot = cross = 0.0
    for pox, poy, pzx, pzy in zip(oxs, oys, zxs, zys, strict=True):
        ox, oy, zx, zy = pox - mox, poy - moy, pzx - mzx, pzy - mzy
        dot += ox * zx + oy * zy
        cross += ox * zy - oy * zx
    rotation = math.atan2(cross, dot)
    c, s = math.cos(rotation), math.sin(rotation)
    return rotation, mzx - (mox * c - moy * s), mzy - (mox * s + moy * c)


def consensus(oxs: list[float], oys: list[float], zxs: list[float], zys: list[float], tolerance: float) -> list[int]:
    """The indices of the points (odometry track onto fixes) that agree with the rotation, of CONSENSUS_ANGLES tried,
    that the most points agree with (ties: the smallest median residual), each rotation with its points' median
    translation. Agreeing is as the trimming judges: within tolerance, or within three times the smallest median
    residual of any rotation (the fixes' own scatter, when the tolerance's noise is smaller)."""
    track_x, track_y = np.asarray(oxs), np.asarray(oys)
    angles = np.linspace(-math.pi, math.pi, CONSENSUS_ANGLES, endpoint=False)[:, np.newaxis]
    c, s = np.cos(angles), np.sin(angles)
    ex = np.asarray(zxs) - (c * track_x - s * track_y)  # one row per rotation
    ey = np.asarray(zys) - (s * track_x + c * track_y)
    ex -= np.median(ex, axis=1, keepdims=True)
    ey -= np.median(ey, axis=1, keepdims=True)
    squared = ex * ex + ey * ey
    medians = np.median(squared, axis=1)
    # a count, not the median alone, picks the rotation: a robot that stood still before it drove gives most of the
    # window's points one odometry position, whose median residual every rotation shares
    inside = squared <= max(9.0 * float(medians.min()), tolerance * tolerance)
    counts = inside.sum(axis=1)
    tied = np.flatnonzero(counts == counts.max())
    best = tied[np.argmin(medians[tied])]
    return [int(i) for i in np.flatnonzero(inside[best])]


def trimmed_rotation_fit(
    oxs: list[float],
    oys: list[float],
    zxs: list[float],
    zys: list[float],
    tolerance: float,
    *,
    min_points: int = MIN_TRIMMED_POINTS,
) -> tuple[float, float, float, float, FixSpread] | None:
    """fit_rotation of the odometry track (oxs, oys) onto the fixes (zxs, zys) with outliers trimmed, and how certain
    its rotation is.

    Returns (rotation, its standard deviation, tx, ty, the residuals' spread) or None when fewer than min_points
    remain or the track is too short or too inconsistent.
    """
    count = len(oxs)
    hypot = math.hypot
    keep = list(range(count))
    robust = False
    for _ in range(MAX_TRIM_PASSES + 1):
        fitted = keep
        n = len(fitted)
        if n < min_points:
            return None
        fitted_x, fitted_y = [oxs[i] for i in fitted], [oys[i] for i in fitted]
        rotation, tx, ty = fit_rotation(fitted_x, fitted_y, [zxs[i] for i in fitted], [zys[i] for i in fitted])
        c, s = math.cos(rotation), math.sin(rotation)
        ex_all = [pzx - (tx + pox * c - poy * s) for pox, poy, pzx in zip(oxs, oys, zxs, strict=True)]
        ey_all = [pzy - (ty + pox * s + poy * c) for pox, poy, pzy in zip(oxs, oys, zys, strict=True)]
        residuals_all = [hypot(a, b) for a, b in zip(ex_all, ey_all, strict=True)]
        if not robust and max(residuals_all) > tolerance:
            # least squares from all the points can be pulled anywhere by a burst of outliers (a quarter of a
            # window's fixes thrown metres away while the robot stood still turned a start-up fit by 1.4 rad): with
            # any point beyond the tolerance, the trimming starts again from the points of the rotation that the most
            # fixes agree with, and may take back any point the fit then explains
            robust = True
            keep = consensus(oxs, oys, zxs, zys, tolerance)
            continue
        median = sorted(residuals_all[i] for i in fitted)[n // 2]
        bound = max(3.0 * median, tolerance)
        keep = [i for i, e in enumerate(residuals_all) if e <= bound]
        if keep == fitted:
            break
    if n < 0.7 * count:  # too many points off the fit: no trustworthy rotation in this window
        return None
    ex, ey = [ex_all[i] for i in fitted], [ey_all[i] for i in fitted]
    residuals = [residuals_all[i] for i in fitted]
    mox, moy = sum(fitted_x) / n, sum(fitted_y) / n
    spread = 0.0  # of the fitted odometry points about their mean
    for pox, poy in zip(fitted_x, fitted_y, strict=True):
        spread += (pox - mox) * (pox - mox) + (poy - moy) * (poy - moy)
    if spread <= 0.0:
        return None
    noise = max(median / math.sqrt(LN4), 1e-3)
    # the fitted points' residuals (ex, ey of the last pass), normalised by their own power
    power = sum(e * e for e in residuals)
    rho = lag_one_correlation(np.column_stack((ex, ey)), power / (2.0 * (n - 1))) if power > 0.0 else 0.0
    if n < MIN_TRIMMED_POINTS:
        rho = max(rho, 0.0)  # a handful of residuals cannot show that they alternate: no credit for it
    # residuals that persist from fix to fix (a delay not yet learnt, multipath, odometry drift) are worth fewer
    # independent ones, (1 - rho) / (1 + rho) each: the rotation is that much less certain (the AR(1) discount)
    sigma = noise / math.sqrt(spread) * math.sqrt((1.0 + rho) / (1.0 - rho))
    if sigma > 0.5:
        return None
    return rotation, sigma, tx, ty, FixSpread(n, noise * noise, rho)


__all__ = [
    "LN4",
    "FixSpread",
    "HeadingAligner",
    "HeadingCheck",
    "RotationFit",
    "consensus",
    "fit_rotation",
    "trimmed_rotation_fit",
]
