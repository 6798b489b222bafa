"""The self-calibration scorecard: each log judged against the issue's targets, the calibration checks, the command."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
from paths import LIBRSF, REPO
from sim_logs import sim_config

from robotd.cli import main
from robotd.offline.consistency import Consistency
from robotd.offline.experiment import Run
from robotd.offline.metrics import ErrorStats
from robotd.offline.scorecard import Entry, Scorecard, geometry_check, latency_check, librsf_entries
from robotd.offline.scorecard_report import as_json, markdown
from robotd.sim import variants
from robotd.sim.world import scenario_params


def _stats(rmse: float, max_m: float) -> ErrorStats:
    return ErrorStats(
        rmse_m=rmse, max_m=max_m, final_m=0.0, mean_m=rmse, median_m=rmse, samples=100, heading_rmse_deg=None
    )


def _entry(inside_95: float | None, nees_mean: float | None) -> Entry:
    honesty = Consistency(nees_mean, nees_mean, inside_95, 2.0, 0.95, 100)
    metrics: dict[str, ErrorStats | None] = {"ekf": _stats(0.01, 0.03), "ips": _stats(0.02, 0.05)}
    return Entry("random", 1, Run(1, 40.0, metrics, None, {}, None, {"ekf": honesty}))


def test_a_log_is_honest_only_with_the_truth_inside_its_ellipse_often_enough_and_a_mean_nees_in_range() -> None:
    assert _entry(0.95, 2.0).honesty_misses() == []
    assert _entry(0.85, 1.0).honesty_misses() == []  # the bounds belong to the target
    assert _entry(0.80, 2.0).honesty_misses() == ["inside 95 % 0.80 < 0.85"]
    assert _entry(1.0, 0.7).honesty_misses() == ["mean NEES 0.70 outside [1, 4]"]  # too conservative is dishonest too
    assert len(_entry(0.5, 9.0).honesty_misses()) == 2
    assert _entry(None, None).honesty_misses() != []  # nothing scored is no pass


def test_the_latency_check_scores_the_learnt_delay_against_the_variants_true_one() -> None:
    config = sim_config()
    check = latency_check(config, 1)
    low, high = variants.build("latency", config, scenario_params(config.sim), 2, 1).world.sim.ips_latency_s
    true_ms = round(0.5 * (low + high) * 1e3)
    assert f"true {true_ms} ms" in check.detail
    # the filter starts from marvelmind.default_latency_s: the check measures what it learnt, not its prior
    assert check.measured < abs(config.marvelmind.default_latency_s - 0.5 * (low + high))
    assert check.met == (check.measured <= 0.015)


def test_the_geometry_check_measures_what_the_calibration_wins_back() -> None:
    config = sim_config()
    calibrated = geometry_check(config, 3)  # the true wheel radius about 10 % above the configured one
    uncalibrated = geometry_check(dataclasses.replace(config, ekf=dataclasses.replace(config.ekf, calibrate=False)), 3)
    assert "radius +9.7%" in calibrated.detail
    assert uncalibrated.measured > calibrated.measured
    assert calibrated.measured <= 1.2


@pytest.mark.skipif(not LIBRSF.is_dir(), reason="the shared libRSF dataset is not beside the repository")
def test_the_librsf_logs_come_in_every_kind_of_fixes_for_every_seed() -> None:
    entries, note = librsf_entries(LIBRSF, sim_config(), [2])
    assert [entry.family for entry in entries] == ["libRSF clean", "libRSF untimed", "libRSF harsh"]
    assert "CC BY-SA" in note
    for entry in entries:
        assert entry.run.metrics["ekf"] is not None
        assert entry.run.consistency["ekf"].nees_mean is not None


def test_librsf_without_its_folder_is_skipped_with_the_reason(tmp_path: Path) -> None:
    entries, note = librsf_entries(tmp_path / "missing", sim_config(), [1])
    assert entries == []
    assert "not found" in note


def test_a_row_says_when_robotds_largest_error_came() -> None:
    # where a maximum falls (the drive-off, the end of a gap) says why a log misses: the card shows it, measured
    entry = _entry(0.95, 2.0)
    timed = dataclasses.replace(entry, run=dataclasses.replace(entry.run, ekf_worst_at_s=3.26))
    card = Scorecard("config/sim.yaml", (1,), 1, [timed, entry], [], "")
    header, rule, *rows = [
        line for line in markdown(card).splitlines() if line.startswith(("| log", "|---", "| random"))
    ]
    at = header.split(" | ").index("max at (s)")
    assert len(rule.split("|")) == len(header.split("|"))
    assert rows[0].split(" | ")[at] == "3.3"
    assert rows[1].split(" | ")[at] == "–"  # no time: no value
    assert [log["ekf_worst_at_s"] for log in as_json(card)["logs"]] == [3.26, None]


def test_the_command_writes_a_card_whose_verdicts_count_its_rows(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = str(REPO / "config" / "sim.yaml")
    status = main(["scorecard", "--only", "twist", "harsh", "--seeds", "1", "--config", config, "--out", str(tmp_path)])
    assert status == 0
    card = json.loads((tmp_path / "scorecard.json").read_text(encoding="utf-8"))
    assert [log["family"] for log in card["logs"]] == ["twist", "harsh"]
    assert all(0.0 < log["ekf_worst_at_s"] < 60.0 for log in card["logs"])  # within the one-loop run
    assert sorted(check["target"] for check in card["calibration_checks"]) == ["geometry", "latency"]
    met = sum(1 for log in card["logs"] if not log["baseline_misses"])
    honest = sum(1 for log in card["logs"] if not log["honesty_misses"])
    markdown = (tmp_path / "scorecard.md").read_text(encoding="utf-8")
    assert f"met on {met} of 2" in markdown
    assert f"met on {honest} of 2" in markdown
    assert markdown.count("\n| twist | 1 |") == 1
    summary = (tmp_path / "summary.md").read_text(encoding="utf-8")  # the README's copy: verdicts, no rows
    assert f"met on {met} of 2" in summary
    assert "\n| twist | 1 |" not in summary
    assert "Against the baselines" in capsys.readouterr().out


def test_the_command_refuses_no_seeds(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["scorecard", "--seeds", "0", "--out", str(tmp_path)]) == 2
    assert "--seeds must be at least 1" in capsys.readouterr().err
