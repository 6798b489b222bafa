"""`robotd experiment` end to end on 2 seeds of a 1-loop square: its numbers against an independent computation."""

from __future__ import annotations

import json
import math
import statistics
import struct
from pathlib import Path

import numpy as np
import pytest
from paths import REPO

from robotd import cli
from robotd.config.model import RobotdConfig, load
from robotd.logs.sensorlog import read_log
from robotd.offline.experiment import METRICS, PAPER_MAX_M, Experiment, run_experiment, run_seeds
from robotd.offline.experiment_report import LABELS, results_markdown, write_results
from robotd.offline.metrics import ErrorStats
from robotd.offline.replay import METHODS, replay

SIM_CONFIG = REPO / "config" / "sim.yaml"
LIBRSF = REPO.parent / "shared" / "datasets" / "librsf_labyrinth_uwb"
SEEDS = (1, 2)
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def config() -> RobotdConfig:
    return load(SIM_CONFIG)


@pytest.fixture(scope="module")
def experiment(config: RobotdConfig) -> Experiment:
    return run_experiment(config, "square", SEEDS, 1, config_name="config/sim.yaml", librsf_folder=LIBRSF)


@pytest.fixture(scope="module")
def independent(config: RobotdConfig, tmp_path_factory: pytest.TempPathFactory) -> dict[int, dict[str, ErrorStats]]:
    """Each seed the long way: `robotd simulate` writes the log file, `replay` reads it back."""
    folder = tmp_path_factory.mktemp("logs")
    per_seed = {}
    for seed in SEEDS:
        log = folder / f"seed{seed}.jsonl"
        argv = [
            "simulate",
            "square",
            "--loops",
            "1",
            "--seed",
            str(seed),
            "--out",
            str(log),
            "--config",
            str(SIM_CONFIG),
        ]
        assert cli.main(argv) == 0
        metrics = replay(read_log(log), config).metrics
        assert metrics is not None
        per_seed[seed] = {name: stats for name, stats in metrics.items() if stats is not None}
    return per_seed


def png_size(path: Path) -> tuple[int, int]:
    """Width and height from a PNG's IHDR chunk; fails on anything that is not a PNG."""
    data = path.read_bytes()
    assert data[:8] == PNG_SIGNATURE, f"{path} is not a PNG"
    assert data[12:16] == b"IHDR"
    width, height = struct.unpack(">II", data[16:24])
    return width, height


def test_each_seed_scores_as_simulate_then_replay_on_the_written_log(
    experiment: Experiment, independent: dict[int, dict[str, ErrorStats]]
) -> None:
    assert [run.seed for run in experiment.runs] == list(SEEDS)
    for run in experiment.runs:
        assert run.seed is not None
        for method in METHODS:
            assert run.metrics[method] == independent[run.seed][method], (run.seed, method)


def test_summary_is_mean_sample_std_min_max_of_the_seeds(
    experiment: Experiment, independent: dict[int, dict[str, ErrorStats]]
) -> None:
    for method in METHODS:
        for metric in METRICS:
            values = [getattr(independent[seed][method], metric) for seed in SEEDS]
            spread = experiment.summary[method].get(metric)
            if any(v is None for v in values):
                assert spread is None, (method, metric)
                continue
            assert spread is not None, (method, metric)
            arr = np.array(values, dtype=np.float64)
            assert spread.n == len(SEEDS)
            assert spread.mean == pytest.approx(arr.mean(), rel=1e-12)
            assert spread.std == pytest.approx(arr.std(ddof=1), rel=1e-9)
            assert spread.min == arr.min()
            assert spread.max == arr.max()
    assert experiment.summary["ips"].get("heading_rmse_deg") is None  # fixes have no heading


def test_worker_processes_give_the_serial_results(config: RobotdConfig, experiment: Experiment) -> None:
    parallel = run_seeds(config, "square", SEEDS, 1, workers=2)
    assert [run.metrics for run in parallel] == [run.metrics for run in experiment.runs]
    assert [run.ekf_worst_at_s for run in parallel] == [run.ekf_worst_at_s for run in experiment.runs]


def test_only_the_first_seed_keeps_its_tracks_for_the_figures(experiment: Experiment) -> None:
    first, second = experiment.runs
    assert first.figures is not None
    assert second.figures is None
    assert set(first.figures.methods) == set(METHODS)
    worst = first.metrics["ekf"]
    assert worst is not None
    assert first.ekf_worst_at_s is not None
    assert 0.0 <= first.ekf_worst_at_s <= first.duration_s


def table_rows(markdown: str) -> dict[str, list[str]]:
    """The first table's rows by their first cell."""
    rows: dict[str, list[str]] = {}
    for line in markdown.split("\n#### ", 1)[0].splitlines():
        if line.startswith("| ") and not line.startswith("| method"):
            cells = [cell.strip() for cell in line.strip("|").split("|")]
            rows[cells[0]] = cells[1:]
    return rows


def test_table_has_every_method_beside_the_papers_published_maxima(experiment: Experiment) -> None:
    markdown = results_markdown(experiment)
    rows = table_rows(markdown)
    assert set(rows) == {LABELS[m] for m in METHODS}
    for method in METHODS:
        cells = rows[LABELS[method]]
        rmse = experiment.summary[method]["rmse_m"]
        maximum = experiment.summary[method]["max_m"]
        assert cells[0] == f"{rmse.mean:.3f} ± {rmse.std:.3f}"
        assert cells[1] == f"{maximum.mean:.3f} ± {maximum.std:.3f}"
        assert cells[2] == f"{maximum.max:.3f}"
        published = PAPER_MAX_M.get("paper_ekf" if method == "ekf" else method, "–")  # the paper had no gated EKF
        assert cells[-1].startswith(str(published))
        # the filters' honesty beside their accuracy; odometry and the raw fixes claim no covariance
        inside, nees = cells[5], cells[6]
        if method in {"ekf", "paper_ekf", "gated_ekf"}:
            honest = [run.consistency[method] for run in experiment.runs]
            shares = [h.inside_95 for h in honest if h.inside_95 is not None]
            assert inside == f"{statistics.fmean(shares):.2f} ± {statistics.stdev(shares):.2f}"
            assert nees.startswith(f"{experiment.summary[method]['nees_mean'].mean:.2f} ± ")
        else:
            assert (inside, nees) == ("–", "–")
    assert {"1.3", "4.6", "1.1"} <= {cells[-1].split()[0] for cells in rows.values()}


def test_real_data_row_carries_the_attribution(experiment: Experiment) -> None:
    markdown = results_markdown(experiment)
    if not LIBRSF.is_dir():
        assert experiment.real is None
        assert "real-data row skipped" in markdown
        return
    assert experiment.real is not None
    assert "CC BY-SA 4.0" in markdown
    assert "Tim Pfeifer" in markdown
    ekf = experiment.real.metrics["ekf"]
    assert ekf is not None
    honesty = experiment.real.consistency["ekf"]
    assert honesty.inside_95 is not None
    assert honesty.nees_mean is not None
    row = f"| robotd EKF | {ekf.rmse_m:.3f} | {ekf.max_m:.3f} | {ekf.final_m:.3f} | {honesty.inside_95:.2f} |"
    assert f"{row} {honesty.nees_mean:.2f} |" in markdown


def test_outputs_are_the_table_the_json_and_png_figures(experiment: Experiment, tmp_path: Path) -> None:
    written = write_results(experiment, tmp_path)
    names = {path.name for path in written}
    assert {"results.md", "results.json", "fig6_trajectories.png", "fig7_errors.png"} <= names
    for path in written:
        if path.suffix == ".png":
            width, height = png_size(path)
            assert width >= 600
            assert height >= 600
    data = json.loads((tmp_path / "results.json").read_text(encoding="utf-8"))
    assert data["seeds"] == list(SEEDS)
    ekf = experiment.runs[1].metrics["ekf"]
    assert ekf is not None
    assert math.isclose(data["runs"][1]["metrics"]["ekf"]["max_m"], ekf.max_m, abs_tol=1e-6)
    assert data["summary"]["odometry"]["max_m"]["n"] == len(SEEDS)
    honesty = experiment.runs[1].consistency["ekf"]
    assert data["runs"][1]["consistency"]["ekf"]["inside_95"] == pytest.approx(honesty.inside_95, abs=1e-4)
    assert data["summary"]["ekf"]["nees_mean"]["n"] == len(SEEDS)


def test_command_writes_its_outputs_and_skips_a_missing_dataset(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "results"
    argv = ["experiment", "square", "--loops", "1", "--seeds", "1", "--first-seed", "3", "--workers", "1"]
    argv += ["--out", str(out), "--config", str(SIM_CONFIG), "--librsf", str(tmp_path / "absent"), "--keep-logs"]
    assert cli.main(argv) == 0
    captured = capsys.readouterr()
    assert "| robotd EKF |" in captured.out
    assert "real-data row skipped" in captured.err
    data = json.loads((out / "results.json").read_text(encoding="utf-8"))
    assert data["seeds"] == [3]
    assert "not found" in data["real_data"]["skipped"]
    assert png_size(out / "fig7_errors.png")[0] > 0
    assert read_log(out / "logs" / "seed3.jsonl").meta.source.startswith("robotd simulate square --seed 3")


def test_command_refuses_zero_seeds(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["experiment", "square", "--seeds", "0", "--out", str(tmp_path)]) == 2
    assert "--seeds must be at least 1" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())
