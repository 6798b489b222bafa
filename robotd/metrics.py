"""Position and heading error of estimates against ground truth (the metrics.json of design.md).

Truth is of the robot's centre, sampled at its own times and interpolated linearly (heading on the circle) at each
estimate's time; estimates outside the truth's time span are not scored. Truth without heading (NaN) scores
position only.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class TruthTrack:
    """Ground truth samples, sorted by time."""

    t: FloatArray
    x: FloatArray
    y: FloatArray
    theta: FloatArray  # unwrapped; NaN where unknown

    @classmethod
    def from_samples(cls, samples: Sequence[tuple[float, float, float, float]]) -> TruthTrack:
        """From (t, x, y, theta) samples in any order (theta may be NaN)."""
        arr = np.array(sorted(samples), dtype=np.float64).reshape(-1, 4)
        theta = arr[:, 3]
        if np.all(np.isfinite(theta)):
            theta = np.unwrap(theta)
        return cls(arr[:, 0], arr[:, 1], arr[:, 2], theta)

    @classmethod
    def from_array(cls, samples: FloatArray) -> TruthTrack:
        """From an n x 4 array of (t, x, y, theta) rows in any order: the same track as from_samples."""
        arr = np.asarray(samples, dtype=np.float64).reshape(-1, 4)
        arr = arr[np.lexsort((arr[:, 3], arr[:, 2], arr[:, 1], arr[:, 0]))]
        theta = arr[:, 3]
        if np.all(np.isfinite(theta)):
            theta = np.unwrap(theta)
        return cls(arr[:, 0], arr[:, 1], arr[:, 2], theta)

    @property
    def has_heading(self) -> bool:
        """Whether every sample has a heading."""
        return bool(len(self.theta) > 0 and np.all(np.isfinite(self.theta)))

    def at(self, t: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, npt.NDArray[np.bool_]]:
        """Truth interpolated at times t: x, y, theta (NaN without heading), and which t lie inside the span."""
        inside = (t >= self.t[0]) & (t <= self.t[-1]) if len(self.t) else np.zeros(len(t), dtype=bool)
        x = np.interp(t, self.t, self.x)
        y = np.interp(t, self.t, self.y)
        theta = np.interp(t, self.t, self.theta) if self.has_heading else np.full(len(t), np.nan)
        return x, y, theta, inside


@dataclass(frozen=True, slots=True)
class ErrorStats:
    """Error of one method against truth."""

    rmse_m: float
    max_m: float
    final_m: float
    mean_m: float
    median_m: float
    samples: int
    heading_rmse_deg: float | None

    def as_dict(self) -> dict[str, float | int]:
        """The metrics.json entry."""
        out: dict[str, float | int] = {
            "rmse_m": round(self.rmse_m, 6),
            "max_m": round(self.max_m, 6),
            "final_m": round(self.final_m, 6),
            "mean_m": round(self.mean_m, 6),
            "median_m": round(self.median_m, 6),
            "samples": self.samples,
        }
        if self.heading_rmse_deg is not None:
            out["heading_rmse_deg"] = round(self.heading_rmse_deg, 4)
        return out


def score(
    truth: TruthTrack,
    t: Sequence[float],
    x: Sequence[float],
    y: Sequence[float],
    theta: Sequence[float] | None = None,
) -> ErrorStats | None:
    """Errors of estimates (x, y[, theta]) at times t against truth; None when none lies within the truth's span."""
    ta = np.asarray(t, dtype=np.float64)
    if len(ta) == 0 or len(truth.t) == 0:
        return None
    tx, ty, tth, inside = truth.at(ta)
    if not np.any(inside):
        return None
    ex = np.asarray(x, dtype=np.float64)[inside] - tx[inside]
    ey = np.asarray(y, dtype=np.float64)[inside] - ty[inside]
    err = np.hypot(ex, ey)
    heading: float | None = None
    if theta is not None and truth.has_heading:
        dth = np.asarray(theta, dtype=np.float64)[inside] - tth[inside]
        dth = (dth + math.pi) % (2.0 * math.pi) - math.pi
        heading = math.degrees(float(np.sqrt(np.mean(dth * dth))))
    return ErrorStats(
        rmse_m=float(np.sqrt(np.mean(err * err))),
        max_m=float(np.max(err)),
        final_m=float(err[-1]),
        mean_m=float(np.mean(err)),
        median_m=float(np.median(err)),
        samples=len(err),
        heading_rmse_deg=heading,
    )


def score_fixes(
    truth: TruthTrack, fixes: Sequence[tuple[float, float, float]], offset: tuple[float, float]
) -> ErrorStats | None:
    """Errors of raw fixes (t_meas, x, y) of the beacon at lever arm `offset`, against the robot's centre."""
    if not fixes:
        return None
    t = np.array([f[0] for f in fixes], dtype=np.float64)
    x = np.array([f[1] for f in fixes], dtype=np.float64)
    y = np.array([f[2] for f in fixes], dtype=np.float64)
    if offset != (0.0, 0.0) and truth.has_heading:
        _, _, th, _ = truth.at(t)
        c, s = np.cos(th), np.sin(th)
        x = x - (offset[0] * c - offset[1] * s)
        y = y - (offset[0] * s + offset[1] * c)
    return score(truth, t.tolist(), x.tolist(), y.tolist())


def fit_rotation(
    local: Sequence[tuple[float, float]], world: Sequence[tuple[float, float]]
) -> tuple[float, float, float]:
    """The rotation and translation (theta, tx, ty) taking local points onto world points, least squares."""
    a = np.asarray(local, dtype=np.float64)
    b = np.asarray(world, dtype=np.float64)
    ma, mb = a.mean(axis=0), b.mean(axis=0)
    da, db = a - ma, b - mb
    dot = float(np.sum(da[:, 0] * db[:, 0] + da[:, 1] * db[:, 1]))
    cross = float(np.sum(da[:, 0] * db[:, 1] - da[:, 1] * db[:, 0]))
    theta = math.atan2(cross, dot)
    c, s = math.cos(theta), math.sin(theta)
    return theta, float(mb[0] - (ma[0] * c - ma[1] * s)), float(mb[1] - (ma[0] * s + ma[1] * c))


__all__ = ["ErrorStats", "TruthTrack", "fit_rotation", "score", "score_fixes"]
