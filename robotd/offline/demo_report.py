"""The demo's results: the live daemon's pose stream and the replayed baselines, scored against the simulator's truth.

robotd's EKF is scored as it ran in the daemon (the poses it published, each scored at its own time); odometry
alone, the raw fixes, the paper's EKF and the gated EKF come from replaying the daemon's own sensor log
(`robotd replay`), so every method sees exactly the data the daemon saw.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from robotd.config.model import RobotdConfig
from robotd.logs.sensorlog import read_log
from robotd.offline.experiment import FigureData, Run, published_max, score_log
from robotd.offline.experiment_report import write_figures
from robotd.offline.metrics import ErrorStats, Trajectory, score

LABELS = {
    "odometry": "odometry alone (replayed)",
    "ips": "raw IPS fixes",
    "paper_ekf": "paper's EKF (replayed)",
    "gated_ekf": "gated EKF (replayed)",
    "ekf": "robotd EKF (live daemon)",
}


def live_track(poses_path: Path) -> Trajectory:
    """The pose stream the daemon published, as a track."""
    rows = []
    with poses_path.open(encoding="utf-8") as stream:
        for line in stream:
            pose = json.loads(line)
            if None not in (pose["x"], pose["y"], pose["theta"]):
                rows.append((pose["t"], pose["x"], pose["y"], pose["theta"]))
    arr = np.array(rows, dtype=np.float64).reshape(-1, 4)
    return Trajectory(arr[:, 0], arr[:, 1], arr[:, 2], arr[:, 3])


def live_run(replayed: Run, live: Trajectory) -> Run:
    """The replayed run with robotd's EKF replaced by the live pose stream, scored against the same truth."""
    assert replayed.figures is not None
    truth = replayed.figures.truth
    stats = score(truth, live)
    metrics = {**replayed.metrics, "ekf": stats}
    figures = FigureData(truth, {**replayed.figures.methods, "ekf": live})
    return dataclasses.replace(replayed, metrics=metrics, figures=figures)


def results_table(metrics: dict[str, ErrorStats | None]) -> str:
    """The Markdown results table, beside the paper's published maxima."""
    lines = [
        "| method | RMSE (m) | max (m) | final (m) | heading RMSE (deg) | paper's published max (m) |",
        "|---|--:|--:|--:|--:|--:|",
    ]
    for method, label in LABELS.items():
        stats = metrics.get(method)
        published = published_max(method)
        paper = "-" if published is None else published
        if stats is None:
            lines.append(f"| {label} | - | - | - | - | {paper} |")
            continue
        heading = "-" if stats.heading_rmse_deg is None else f"{stats.heading_rmse_deg:.2f}"
        lines.append(
            f"| {label} | {stats.rmse_m:.3f} | {stats.max_m:.3f} | {stats.final_m:.3f} | {heading} | {paper} |"
        )
    return "\n".join(lines) + "\n"


def report(log_path: Path, poses_path: Path, out_dir: Path, config: RobotdConfig, out: TextIO) -> dict[str, Any]:
    """Score the demo, write results.md, metrics.json and the figures; print the table; return the metrics."""
    replayed = score_log(read_log(log_path), config, seed=None, keep_figures=True)
    run = live_run(replayed, live_track(poses_path))
    table = results_table(run.metrics)
    (out_dir / "results.md").write_text(
        "robotd demo: the paper's square driven through the daemon on the virtual robot\n\n" + table, encoding="utf-8"
    )
    metrics = {name: (stats.as_dict() if stats is not None else None) for name, stats in run.metrics.items()}
    (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n", encoding="utf-8")
    figures = write_figures(run, out_dir, "", "robotd demo: the paper's square through the daemon (virtual robot)")
    out.write("\n" + table + "\n")
    out.write("figures: " + ", ".join(str(p) for p in figures) + "\n")
    return metrics
