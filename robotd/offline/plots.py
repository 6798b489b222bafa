"""Figures in the paper's style: Fig. 6 (trajectories against truth), Fig. 7 (position error over time), heading error.

Pure plotting of arrays already computed; matplotlib is an optional dependency (the `plot` extra), imported here
only, with the non-interactive Agg back-end so that figures render on a headless Pi or CI machine.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from robotd.estimation.ekf import wrap_angle
from robotd.offline.metrics import Trajectory

FloatArray = npt.NDArray[np.float64]

# One colour and style per method, the same in every figure.
STYLES: dict[str, dict[str, object]] = {
    "truth": {"color": "black", "linewidth": 2.0, "label": "ground truth"},
    "odometry": {"color": "tab:orange", "linewidth": 1.2, "label": "odometry (dead reckoning)"},
    "ips": {"color": "tab:green", "linestyle": "none", "marker": ".", "markersize": 2.5, "label": "IPS fixes"},
    "paper_ekf": {"color": "tab:blue", "linewidth": 1.2, "label": "paper's EKF"},
    "gated_ekf": {"color": "tab:purple", "linewidth": 1.0, "linestyle": "--", "label": "gated EKF"},
    "ekf": {"color": "tab:red", "linewidth": 1.4, "label": "robotd EKF"},
}


def _pyplot() -> Any:
    import matplotlib  # noqa: PLC0415  (optional dependency: only the experiment tools plot)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    return plt


def position_error(trajectory: Trajectory, truth: Trajectory) -> FloatArray:
    """Distance from each pose of `trajectory` to truth at the same time (m)."""
    x, y, _, _ = truth.at(trajectory.t)
    return np.asarray(np.hypot(trajectory.x - x, trajectory.y - y), dtype=np.float64)


def heading_error_deg(trajectory: Trajectory, truth: Trajectory) -> FloatArray:
    """Wrapped heading error in degrees (NaN where either has no heading)."""
    _, _, theta, _ = truth.at(trajectory.t)
    return np.asarray(np.degrees(wrap_angle(trajectory.theta - theta)), dtype=np.float64)


def _drawing_order(methods: Mapping[str, Trajectory]) -> list[str]:
    """Methods from the least to the most accurate as drawn: fixes under the filters, robotd's on top."""
    known = [name for name in STYLES if name in methods]
    return [name for name in methods if name not in STYLES] + known


def trajectories(truth: Trajectory, methods: Mapping[str, Trajectory], path: Path, title: str) -> None:
    """Fig. 6: every method's x, y path against truth, equal axes, metres."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7.0, 6.5), dpi=120)
    # truth first and wide, so that a filter lying on it stays visible above it
    ax.plot(truth.x, truth.y, **{**STYLES["truth"], "linewidth": 3.0, "alpha": 0.45})
    ax.plot(truth.x[:1], truth.y[:1], "ko", markersize=6, label="start")
    for name in _drawing_order(methods):
        track = methods[name]
        ax.plot(track.x, track.y, **STYLES.get(name, {"label": name}))
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title)
    ax.grid(visible=True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _off_scale_note(ax: Any, series: Mapping[str, FloatArray], limit: float, unit: str) -> None:
    """Name the methods whose curve leaves the axis, with their peak, in the axis' corner."""
    notes = []
    for name, values in series.items():
        finite = np.abs(values[np.isfinite(values)])
        if len(finite) and float(finite.max()) > limit:
            label = str(STYLES.get(name, {}).get("label", name))
            notes.append(f"{label} off scale, up to {float(finite.max()):.{2 if unit == 'm' else 0}f} {unit}")
    if notes:
        ax.text(
            0.99,
            0.97,
            "\n".join(notes),
            transform=ax.transAxes,
            ha="right",
            va="top",
            fontsize=8,
            bbox={"facecolor": "white", "edgecolor": "none", "alpha": 0.8},
        )


def errors_over_time(
    truth: Trajectory,
    methods: Mapping[str, Trajectory],
    path: Path,
    title: str,
    *,
    zoom: tuple[str, ...] = ("paper_ekf", "ekf"),
    target_m: float | None = None,
) -> None:
    """Fig. 7 (position error over time, every method), the same zoomed on the filters, then heading error."""
    plt = _pyplot()
    fig, (full, close, heading_ax) = plt.subplots(
        3, 1, figsize=(8.0, 8.5), dpi=120, sharex=True, gridspec_kw={"height_ratios": [1.2, 1.0, 1.0]}
    )
    t0 = float(truth.t[0])
    order = _drawing_order(methods)
    position = {name: position_error(methods[name], truth) for name in order}
    heading = {name: heading_error_deg(methods[name], truth) for name in order}
    for name in order:
        style = dict(STYLES.get(name, {"label": name}))
        t = methods[name].t - t0
        full.plot(t, position[name], **style)
        if name in zoom:
            close.plot(t, position[name], **style)
        if np.isfinite(heading[name]).any():
            heading_ax.plot(t, heading[name], **style)
    full.set_ylabel("position error (m)")
    full.set_title(title)
    full.legend(loc="upper left", fontsize=8)
    # the zoom fits the most accurate filter (the last drawn), so its error is readable next to metre-sized ones
    focus = [position[name] for name in order if name in zoom]
    peak = float(np.nanmax(focus[-1])) if focus and np.isfinite(focus[-1]).any() else 0.1
    top = max(0.1, 1.3 * peak, 1.15 * (target_m or 0.0))
    if target_m is not None:
        close.axhline(target_m, color="grey", linestyle="--", linewidth=1.0, label=f"target {target_m} m")
        close.legend(loc="upper left", fontsize=8)
    close.set_ylim(0.0, top)
    close.set_ylabel("position error (m),\nfilters close up")
    _off_scale_note(close, {name: position[name] for name in order if name in zoom}, top, "m")
    finite_heading = [np.abs(h[np.isfinite(h)]) for name, h in heading.items() if name in ("odometry", zoom[-1])]
    spread = max((float(h.max()) for h in finite_heading if len(h)), default=5.0)
    limit = max(5.0, 1.2 * spread)
    heading_ax.set_ylim(-limit, limit)
    heading_ax.set_ylabel("heading error (deg)")
    heading_ax.set_xlabel("time (s)")
    _off_scale_note(heading_ax, heading, limit, "deg")
    if not np.isfinite(truth.theta).any():
        heading_ax.text(0.5, 0.5, "no heading in the ground truth", transform=heading_ax.transAxes, ha="center")
    for ax in (full, close, heading_ax):
        ax.grid(visible=True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
