"""`robotd simulate-fixes`: a recorded log's fixes replaced by the virtual hedgehog's, measured on its truth."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from paths import LIBRSF, SIM_CONFIG
from sim_logs import simulated

from robotd import cli
from robotd.config.model import load
from robotd.logs.sensorlog import IpsFix, IpsLost, LogWriter, Meta, Truth, TwistSample, read_log
from robotd.offline.metrics import Trajectory
from robotd.sim.refix import HARSH_OUTAGE_S, TruthError, refixed
from robotd.sim.world import ips_params

CONFIG = load(SIM_CONFIG)


def _fix_errors(events: list[object], truth: Trajectory, offset: tuple[float, float]) -> np.ndarray:
    """Each fix's distance from the true beacon at its measurement time."""
    errors = []
    for fix in events:
        if isinstance(fix, IpsFix):
            x, y, theta, _ = truth.at(np.array([fix.t_meas]))
            bx = x[0] + offset[0] * math.cos(theta[0]) - offset[1] * math.sin(theta[0])
            by = y[0] + offset[0] * math.sin(theta[0]) + offset[1] * math.cos(theta[0])
            errors.append(math.hypot(fix.x - bx, fix.y - by))
    return np.array(errors)


def test_clean_fixes_measure_the_beacon_on_the_truth_with_the_configured_noise_and_keep_the_rest() -> None:
    log = simulated(CONFIG, 3)  # the virtual robot's log: its own fixes are replaced
    offset = (0.1, 0.05)
    params = ips_params(CONFIG.sim)
    events = refixed(log.events, params, "clean", 7, offset)
    assert [e for e in events if not isinstance(e, IpsFix | IpsLost)] == [
        e for e in log.events if not isinstance(e, IpsFix | IpsLost)
    ]
    assert [e.t for e in events] == sorted(e.t for e in events)
    truth = Trajectory.from_samples([(e.t, e.x, e.y, e.theta) for e in log.events if isinstance(e, Truth)])
    fixes = [e for e in events if isinstance(e, IpsFix)]
    span = truth.t[-1] - truth.t[0]
    assert 0.8 * params.rate_hz * span < len(fixes) <= 1.1 * params.rate_hz * span
    assert all(params.latency_s[0] <= f.t - f.t_meas <= params.latency_s[1] + 0.01 for f in fixes)
    errors = _fix_errors(list(events), truth, offset)
    # a 2-D Gaussian's radial RMS is sqrt(2) sigma: placed with the offset turned by the heading, nothing thrown
    assert float(np.sqrt(np.mean(errors**2))) == pytest.approx(math.sqrt(2.0) * params.noise_m, rel=0.15)
    assert errors.max() < 6.0 * params.noise_m
    assert refixed(log.events, params, "clean", 7, offset) == events  # the seed decides everything
    assert refixed(log.events, params, "clean", 8, offset) != events


def test_untimed_and_harsh_fixes_carry_no_measurement_time_and_harsh_ones_have_bursts_and_an_outage() -> None:
    log = simulated(CONFIG, 3, loops=3)  # minutes: bursts come about 2.4 times a minute
    params = ips_params(CONFIG.sim)
    untimed = [e for e in refixed(log.events, params, "untimed", 7, (0.0, 0.0)) if isinstance(e, IpsFix)]
    assert untimed
    assert all(math.isnan(f.t_meas) for f in untimed)
    harsh = refixed(log.events, params, "harsh", 7, (0.0, 0.0))
    fixes = [e for e in harsh if isinstance(e, IpsFix)]
    assert all(math.isnan(f.t_meas) for f in fixes)
    gaps = np.diff([f.t for f in fixes])
    assert gaps.max() >= HARSH_OUTAGE_S - 0.5  # the outage in the middle (packets flagged lost, no fix)
    assert any(isinstance(e, IpsLost) for e in harsh)
    truth = Trajectory.from_samples([(e.t, e.x, e.y, e.theta) for e in log.events if isinstance(e, Truth)])
    x, y, _, _ = truth.at(np.array([f.t for f in fixes]))  # at arrival: within a latency's travel, or thrown
    thrown = np.hypot(np.array([f.x for f in fixes]) - x, np.array([f.y for f in fixes]) - y) > 0.9
    assert thrown.sum() >= 3  # outlier bursts, thrown 1-4.6 m (a burst lasts 0.5-2.5 s: several fixes)


def test_a_log_without_truth_or_without_the_heading_an_offset_needs_is_refused() -> None:
    twist = TwistSample(0.0, 0.1, 0.0, 0.0)
    params = ips_params(CONFIG.sim)
    with pytest.raises(TruthError, match="fewer than two truth samples"):
        refixed([twist], params, "clean", 1, (0.0, 0.0))
    headless = [Truth(0.0, 0.0, 0.0, math.nan), Truth(1.0, 0.1, 0.0, math.nan)]
    with pytest.raises(TruthError, match="no heading"):
        refixed(headless, params, "clean", 1, (0.1, 0.0))
    assert any(isinstance(e, IpsFix) for e in refixed(headless, params, "clean", 1, (0.0, 0.0)))
    with pytest.raises(ValueError, match="unknown kind"):
        refixed(headless, params, "noisy", 1, (0.0, 0.0))


@pytest.mark.skipif(not LIBRSF.is_dir(), reason="the shared libRSF dataset is not beside the repository")
def test_the_cli_turns_a_real_robots_log_into_one_robotd_replays(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    real = tmp_path / "librsf.jsonl"
    assert cli.main(["convert-librsf", str(LIBRSF), "--out", str(real)]) == 0
    out = tmp_path / "librsf_untimed.jsonl"
    args = ["simulate-fixes", str(real), "--out", str(out), "--kind", "untimed", "--seed", "4"]
    assert cli.main([*args, "--config", str(SIM_CONFIG)]) == 0
    assert "untimed fixes (seed 4)" in capsys.readouterr().out
    log = read_log(out)
    assert log.problems == []
    assert "Tim Pfeifer" in log.meta.source  # the licence's attribution is kept
    assert "simulate-fixes --kind untimed --seed 4" in log.meta.source
    original = read_log(real)
    assert [e for e in log.events if isinstance(e, TwistSample)] == [
        e for e in original.events if isinstance(e, TwistSample)
    ]
    assert cli.main(["replay", str(out), "--out", str(tmp_path / "replay")]) == 0
    assert (tmp_path / "replay" / "metrics.json").is_file()


def test_the_cli_says_what_is_wrong_with_its_input(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = str(tmp_path / "out.jsonl")
    assert cli.main(["simulate-fixes", str(tmp_path / "missing.jsonl"), "--out", out]) == 66
    assert "missing.jsonl" in capsys.readouterr().err
    no_truth = tmp_path / "no_truth.jsonl"
    with no_truth.open("w", encoding="utf-8") as stream:
        LogWriter(stream, Meta()).write(TwistSample(0.0, 0.1, 0.0, 0.0))
    assert cli.main(["simulate-fixes", str(no_truth), "--out", out, "--config", str(SIM_CONFIG)]) == 65
    assert "no truth to measure fixes on" in capsys.readouterr().err
    bad_offset = tmp_path / "bad_offset.jsonl"
    with bad_offset.open("w", encoding="utf-8") as stream:
        writer = LogWriter(stream, Meta(robot={"ips_offset": [1e300, 0.0]}))
        for t in (0.0, 1.0):
            writer.write(Truth(t, 0.1 * t, 0.0, 0.0))
    assert cli.main(["simulate-fixes", str(bad_offset), "--out", out, "--config", str(SIM_CONFIG)]) == 65
    assert "meta.robot.ips_offset: must be a list of 2 numbers" in capsys.readouterr().err  # as robotd replay says
    assert not Path(out).exists()
