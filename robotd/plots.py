"""Figures in the paper's style: Fig. 6 (trajectories against truth), Fig. 7 (position error over time), heading error.

Pure plotting of arrays already computed; matplotlib is an optional dependency (the `plot` extra), imported here
only, with the non-interactive Agg back-end so that figures render on a headless Pi or CI machine.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

# One colour and style per method, the same in every figure.
STYLES: dict[str, dict[str, object]] = {
    "truth": {"color": "black", "linewidth": 2.0, "label": "ground truth"},
    "odometry": {"color": "tab:orange", "linewidth": 1.2, "label": "odometry (dead reckoning)"},
    "ips": {"color": "tab:green", "linestyle": "none", "marker": ".", "markersize": 2.5, "label": "IPS fixes"},
    "paper_ekf": {"color": "tab:blue", "linewidth": 1.2, "label": "paper's EKF"},
    "ekf": {"color": "tab:red", "linewidth": 1.4, "label": "robotd EKF"},
}


@dataclass(frozen=True, slots=True)
class Track:
    """A time series of planar poses; theta may be all NaN where a method has no heading (IPS fixes)."""

    t: FloatArray
    x: FloatArray
    y: FloatArray
    theta: FloatArray


def _pyplot() -> Any:
    import matplotlib  # noqa: PLC0415  (optional dependency: only the experiment tools plot)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    return plt


def interpolate_truth(truth: Track, t: FloatArray) -> Track:
    """Truth at the times `t` (linear in x, y; heading unwrapped before interpolating)."""
    theta = np.interp(t, truth.t, np.unwrap(truth.theta)) if np.isfinite(truth.theta).all() else np.full_like(t, np.nan)
    return Track(t, np.interp(t, truth.t, truth.x), np.interp(t, truth.t, truth.y), theta)


def position_error(track: Track, truth: Track) -> FloatArray:
    """Distance from each pose of `track` to truth at the same time (m)."""
    ref = interpolate_truth(truth, track.t)
    return np.asarray(np.hypot(track.x - ref.x, track.y - ref.y), dtype=np.float64)


def heading_error_deg(track: Track, truth: Track) -> FloatArray:
    """Wrapped heading error in degrees (NaN where either has no heading)."""
    ref = interpolate_truth(truth, track.t)
    wrapped = np.angle(np.exp(1j * (track.theta - ref.theta)))
    return np.asarray(np.degrees(wrapped), dtype=np.float64)


def trajectories(truth: Track, methods: Mapping[str, Track], path: Path, title: str) -> None:
    """Fig. 6: every method's x, y path against truth, equal axes, metres."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7.0, 6.5), dpi=120)
    for name, track in methods.items():
        ax.plot(track.x, track.y, **STYLES.get(name, {"label": name}))
    ax.plot(truth.x, truth.y, **STYLES["truth"])
    ax.plot(truth.x[:1], truth.y[:1], "ko", markersize=6)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title)
    ax.grid(visible=True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def errors_over_time(truth: Track, methods: Mapping[str, Track], path: Path, title: str) -> None:
    """Fig. 7 (position error over time for each method) above the heading error over time."""
    plt = _pyplot()
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(8.0, 6.5), dpi=120, sharex=True)
    t0 = float(truth.t[0])
    for name, track in methods.items():
        style = dict(STYLES.get(name, {"label": name}))
        top.plot(track.t - t0, position_error(track, truth), **style)
        heading = heading_error_deg(track, truth)
        if np.isfinite(heading).any():
            bottom.plot(track.t - t0, heading, **style)
    top.set_ylabel("position error (m)")
    top.set_title(title)
    top.grid(visible=True, alpha=0.3)
    top.legend(loc="upper left", fontsize=8)
    bottom.set_ylabel("heading error (deg)")
    bottom.set_xlabel("time (s)")
    bottom.grid(visible=True, alpha=0.3)
    if not np.isfinite(truth.theta).any():
        bottom.text(0.5, 0.5, "no heading in the ground truth", transform=bottom.transAxes, ha="center")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
