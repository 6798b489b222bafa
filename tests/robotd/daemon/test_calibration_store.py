"""The learnt calibration and noise survive a restart: saved atomically, loaded with the uncertainty widened, never
fatal."""

from __future__ import annotations

import json
import logging
from dataclasses import astuple
from pathlib import Path

import pytest

from robotd.config.model import EkfConfig
from robotd.daemon import calibration_store
from robotd.daemon.calibration_store import CalibrationKeeper
from robotd.estimation.calibration import Calibration
from robotd.estimation.estimator import Estimator, LearntNoise
from robotd.kinematics import Geometry


def test_a_saved_calibration_starts_the_next_estimator_calibrated(tmp_path: Path) -> None:
    path = str(tmp_path / "calibration.json")
    learnt = Calibration(1.1, 0.9, 1.05, 0.12, 0.004, (0.005, 0.01, 0.01, 0.003, 0.003), 40)
    keeper = CalibrationKeeper(path)
    keeper.maybe_save(learnt, 100.0)
    saved = calibration_store.load(path)
    assert saved is not None
    loaded = saved.calibration
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


def _at_rest_with_a_shared_error(saved: calibration_store.Saved | None) -> float:
    """The NEES of the true position (the origin) after 2 s of fixes sharing one 0.1 m error, the robot at rest."""
    estimator = Estimator(
        EkfConfig(),
        Geometry(),
        (0.0, 0.0),
        6800,
        calibration=None if saved is None else saved.calibration,
        noise=None if saved is None else saved.noise,
    )
    for k in range(32):
        t = k / 16.0
        estimator.on_twist(t, 0.0, 0.0, 0.0)
        estimator.on_fix(t, 0.1, 0.0, t)
    estimate = estimator.pose()
    return estimate.x**2 / estimate.cov[0] + estimate.y**2 / estimate.cov[4]


def test_the_fixes_judgement_and_the_learnt_noise_survive_a_restart(tmp_path: Path) -> None:
    path = str(tmp_path / "calibration.json")
    # a run that judged its fixes' errors to persist (a wall's echo): 0.1 m, lag-one correlation 0.8
    judged = Calibration(1.02, 1.0, 0.98, 0.05, 0.0, (0.01,) * 5, 12, 0.1**2 * 0.8, 0.8, 0.1**2)
    calibration_store.save(path, judged, LearntNoise(0.1**2, 0.4, 2.5))
    saved = calibration_store.load(path)
    assert saved is not None
    assert saved.noise is not None
    assert astuple(saved.noise) == pytest.approx((0.1**2, 0.4, 2.5))
    loaded = saved.calibration
    assert (loaded.fix_var, loaded.fix_correlation, loaded.fix_correlated_var) == pytest.approx((0.01, 0.8, 0.008))
    restarted = Estimator(EkfConfig(), Geometry(), (0.0, 0.0), 6800, calibration=loaded, noise=saved.noise)
    assert restarted.calibration.fix_information == pytest.approx(0.2 / 1.8)
    assert astuple(restarted.learnt_noise) == pytest.approx((0.01, 0.4, 2.5))
    # started from what the run before learnt, the filter does not trust fixes that share their error from its first
    # fixes on; started from the configuration alone, the truth lies far outside its ellipse
    assert _at_rest_with_a_shared_error(saved) <= 5.991  # the 95 % ellipse, 2 dof
    assert _at_rest_with_a_shared_error(None) > 5.991


def test_a_file_from_before_the_noise_was_kept_loads_without_it(tmp_path: Path) -> None:
    path = tmp_path / "calibration.json"
    old = {"format": "robotd-calibration", "kx": 1.1, "ky": 1.0, "kw": 1.0, "latency_s": 0.05, "time_error_s": 0.0}
    path.write_text(json.dumps(old | {"sigmas": [0.01] * 5, "windows": 4}), encoding="utf-8")
    saved = calibration_store.load(str(path))
    assert saved is not None
    assert saved.noise is None
    assert (saved.calibration.kx, saved.calibration.fix_correlation) == (1.1, 0.0)
    estimator = Estimator(EkfConfig(), Geometry(), (0.0, 0.0), 6800, calibration=saved.calibration)
    noise = estimator.learnt_noise
    assert (noise.ips_var, noise.process_noise_scale) == pytest.approx((EkfConfig().ips_sigma_m ** 2, 1.0))


def test_a_file_from_before_the_headings_noise_scale_takes_the_positions(tmp_path: Path) -> None:
    # one scale was learnt for both then: it is where the heading's starts
    path = tmp_path / "calibration.json"
    calibration_store.save(str(path), Calibration(windows=2), LearntNoise(0.03**2, 0.2, 3.0))
    data = json.loads(path.read_text())
    del data["heading_noise_scale"]
    path.write_text(json.dumps(data), encoding="utf-8")
    saved = calibration_store.load(str(path))
    assert saved is not None
    assert saved.noise is not None
    assert astuple(saved.noise) == pytest.approx((0.03**2, 0.2, 0.2))


@pytest.mark.parametrize(
    "field",
    [
        {"fix_correlation": 1.5},
        {"fix_var": -1.0},
        {"ips_sigma_m": 0.0, "process_noise_scale": 1.0},
        {"heading_noise_scale": -1.0},
    ],
)
def test_a_saved_judgement_out_of_range_costs_a_warning(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, field: dict[str, float]
) -> None:
    path = tmp_path / "calibration.json"
    calibration_store.save(str(path), Calibration(windows=2), LearntNoise(0.03**2))
    path.write_text(json.dumps(json.loads(path.read_text()) | field), encoding="utf-8")
    with caplog.at_level(logging.WARNING):
        assert calibration_store.load(str(path)) is None
    assert "calibration file" in caplog.text
