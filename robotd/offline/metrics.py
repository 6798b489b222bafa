"""Trajectories, and the position and heading error of estimates against ground truth (the metrics.json of design.md).

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

from robotd.estimation.ekf import wrap_angle

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class Trajectory:
    """Planar poses over time: t (s), x, y (m), theta (rad; NaN where a method has no heading, as raw fixes)."""

    t: FloatArray
    x: FloatArray
    y: FloatArray
    theta: FloatArray

    @classmethod
    def of(cls, t: Sequence[float], x: Sequence[float], y: Sequence[float], theta: Sequence[float]) -> Trajectory:
        """From four sequences of the same length."""
        return cls(*(np.asarray(column, dtype=np.float64) for column in (t, x, y, theta)))

    @classmethod
    def from_samples(cls, samples: Sequence[tuple[float, float, float, float]]) -> Trajectory:
        """From (t, x, y, theta) samples in any order (truth: theta may be NaN)."""
        arr = np.array(sorted(samples), dtype=np.float64).reshape(-1, 4)
        return cls(arr[:, 0], arr[:, 1], arr[:, 2], arr[:, 3])

    def __len__(self) -> int:
        return len(self.t)

    @property
    def has_heading(self) -> bool:
        """Whether every pose has a heading."""
        return bool(len(self.theta) > 0 and np.all(np.isfinite(self.theta)))

    def at(self, t: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, npt.NDArray[np.bool_]]:
        """The poses interpolated at times t (sorted by time), heading on the circle (NaN without heading), and which
        t lie inside the time span."""
        inside = (t >= self.t[0]) & (t <= self.t[-1]) if len(self.t) else np.zeros(len(t), dtype=bool)
        x = np.interp(t, self.t, self.x)
        y = np.interp(t, self.t, self.y)
        theta = np.interp(t, self.t, np.unwrap(self.theta)) if self.has_heading else np.full(len(t), np.nan)
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


def score(truth: Trajectory, estimates: Trajectory) -> ErrorStats | None:
    """Errors of estimates against truth (heading too when both have one); None when none lies within the truth's
    span."""
    if len(estimates) == 0 or len(truth) == 0:
        return None
    tx, ty, tth, inside = truth.at(estimates.t)
    if not np.any(inside):
        return None
    ex = estimates.x[inside] - tx[inside]
    ey = estimates.y[inside] - ty[inside]
    err = np.hypot(ex, ey)
    heading: float | None = None
    if estimates.has_heading and truth.has_heading:
        dth = wrap_angle(estimates.theta[inside] - tth[inside])
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


def fixes_trajectory(
    fixes: Sequence[tuple[float, float, float]], offset: tuple[float, float], truth: Trajectory
) -> Trajectory:
    """Raw fixes (t_meas, x, y) of the beacon at lever arm `offset` moved to the robot's centre with the true heading
    (no heading of their own)."""
    t = np.array([f[0] for f in fixes], dtype=np.float64)
    x = np.array([f[1] for f in fixes], dtype=np.float64)
    y = np.array([f[2] for f in fixes], dtype=np.float64)
    if offset != (0.0, 0.0) and truth.has_heading and len(t):
        _, _, th, _ = truth.at(t)
        c, s = np.cos(th), np.sin(th)
        x = x - (offset[0] * c - offset[1] * s)
        y = y - (offset[0] * s + offset[1] * c)
    return Trajectory(t, x, y, np.full(len(t), np.nan))


__all__ = ["ErrorStats", "Trajectory", "fixes_trajectory", "score"]
