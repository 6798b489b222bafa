"""The learnt calibration survives a restart: saved atomically, loaded with its uncertainty widened, never fatal."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import pytest

from robotd.config.model import EkfConfig
from robotd.daemon import calibration_store
from robotd.daemon.calibration_store import CalibrationKeeper
from robotd.estimation.calibration import Calibration
from robotd.estimation.estimator import Estimator
from robotd.kinematics import Geometry


def test_a_saved_calibration_starts_the_next_estimator_calibrated(tmp_path: Path) -> None:
    path = str(tmp_path / "calibration.json")
    learnt = Calibration(1.1, 0.9, 1.05, 0.12, 0.004, (0.005, 0.01, 0.01, 0.003, 0.003), 40)
    keeper = CalibrationKeeper(path)
    keeper.maybe_save(learnt, 100.0)
    loaded = calibration_store.load(path)
    assert loaded is not None
    assert (loaded.kx, loaded.ky, loaded.kw, loaded.latency_s, loaded.windows) == (1.1, 0.9, 1.05, 0.12, 40)
    assert loaded.sigmas[0] == calibration_store.MIN_SCALE_SIGMA  # the robot may have changed while stopped
    estimator = Estimator(EkfConfig(), Geometry(), (0.0, 0.0), 6800, calibration=loaded)
    assert estimator.calibration.kx == pytest.approx(1.1)
    estimator.on_twist(0.0, 0.0, 0.0, 0.0)
    estimator.on_twist(1.0, 0.2, 0.0, 0.0)
    assert estimator.pose().vx == pytest.approx(0.22)  # the odometry's speed, calibrated


def test_saves_only_new_windows_at_most_once_a_minute_unless_forced(tmp_path: Path) -> None:
    path = tmp_path / "calibration.json"
    keeper = CalibrationKeeper(str(path))
    keeper.maybe_save(Calibration(windows=1), 0.0)
    assert json.loads(path.read_text())["windows"] == 1
    keeper.maybe_save(Calibration(windows=2), 10.0)
    assert json.loads(path.read_text())["windows"] == 1
    keeper.maybe_save(Calibration(windows=2), 10.0, force=True)  # the daemon's way out
    assert json.loads(path.read_text())["windows"] == 2
    assert not (tmp_path / "calibration.json.tmp").exists()


def test_a_damaged_or_unwritable_file_costs_a_warning_not_the_daemon(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "calibration.json"
    path.write_text("{half a file", encoding="utf-8")
    with caplog.at_level(logging.WARNING):
        assert calibration_store.load(str(path)) is None
        assert calibration_store.load(str(tmp_path / "missing.json")) is None
        assert calibration_store.load("") is None
        keeper = CalibrationKeeper(str(tmp_path / "no" / "such" / "dir" / "calibration.json"))
        keeper.maybe_save(Calibration(windows=3), 0.0)
    assert keeper.failures == 1
    assert sum("calibration" in record.message for record in caplog.records) == 2
