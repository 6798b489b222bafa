"""`robotd tune`: noise fitted on one log improves the replay of another it never saw."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import msgspec
import pytest
import yaml
from sim_logs import sim_config, simulated, simulated_text

from robotd import cli
from robotd.config.model import RobotdConfig, parse
from robotd.logs.sensorlog import SensorLog
from robotd.offline.replay import replay
from robotd.offline.tune import score, tune, yaml_snippet


def _overconfident(config: RobotdConfig) -> RobotdConfig:
    """The configuration with odometry noise ten times too small and its scales taken as known to 1 %: a filter that
    believes its wheels too much."""
    ekf = dataclasses.replace(
        config.ekf, odom_along_sigma_m=0.002, odom_across_sigma_m=0.003, slip_heading_sigma_rad=0.005, scale_sigma=0.01
    )
    return dataclasses.replace(config, ekf=ekf)


def test_tuning_on_one_log_improves_the_replay_of_a_held_out_log() -> None:
    robot = sim_config(lateral_efficiency=0.85)  # the same robot drives both runs
    fitted_on, held_out = (simulated(robot, seed, loops=1, scenario="random") for seed in (1, 2))
    start = _overconfident(robot)
    result = tune([fitted_on], start)
    assert result.changes
    assert result.ips_offset is None  # the lever arm only on request
    assert result.after[0].nll < result.before[0].nll
    tuned = dataclasses.replace(start, ekf=result.ekf)
    before_fit, _ = score(held_out, start, start.ekf)
    after_fit, _ = score(held_out, tuned, tuned.ekf)
    assert after_fit.nll < before_fit.nll  # the held-out fixes are more likely
    before, after = replay(held_out, start), replay(held_out, tuned)
    honest_before, honest_after = before.consistency["ekf"].inside_95, after.consistency["ekf"].inside_95
    assert honest_before is not None
    assert honest_after is not None
    assert honest_after > honest_before  # and its covariance more honest against truth it never saw
    assert after.metrics is not None
    assert before.metrics is not None
    ours, theirs = after.metrics["ekf"], before.metrics["ekf"]
    assert ours is not None
    assert theirs is not None
    assert ours.rmse_m <= 1.05 * theirs.rmse_m


def test_the_command_prints_what_it_changed_and_writes_a_snippet_the_config_accepts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log = tmp_path / "drive.jsonl"
    log.write_text(simulated_text(sim_config(), 3, scenario="random"), encoding="utf-8")
    start = tmp_path / "start.yaml"
    start.write_text("ekf: {odom_along_sigma_m: 0.002, slip_heading_sigma_rad: 0.005}\n", encoding="utf-8")
    snippet = tmp_path / "tuned.yaml"
    assert cli.main(["tune", str(log), "--config", str(start), "--out", str(snippet)]) == 0
    out = capsys.readouterr().out
    assert "ekf.odom_along_sigma_m: 0.002 ->" in out
    parsed = parse(snippet.read_text())  # the configuration's own validation takes it
    fitted = yaml.safe_load(snippet.read_text())["ekf"]
    changed = [line.strip()[len("ekf.") :] for line in out.splitlines() if line.startswith("  ekf.")]
    assert len(changed) >= 2
    for line in changed:  # the snippet holds what the printout says changed, and the configuration reads it so
        key, values = line.split(": ", 1)
        before, after = values.split(" -> ")
        assert yaml.safe_load(after) == fitted[key] != yaml.safe_load(before)
        value = getattr(parsed.ekf, key)
        assert (list(value) if isinstance(value, tuple) else value) == fitted[key]
    assert cli.main(["tune", str(tmp_path / "missing.jsonl")]) == 66


def _undeclared(log: SensorLog) -> SensorLog:
    """The log as a recorder that declared no lever arm writes it (the replay then takes the configuration's)."""
    robot = {key: value for key, value in log.meta.robot.items() if key != "ips_offset"}
    return SensorLog(msgspec.structs.replace(log.meta, robot=robot), log.events, log.problems, log.unknown_types, [])


def test_a_lever_arm_left_out_of_the_configuration_is_found_on_a_turning_robot_and_fixes_a_held_out_replay() -> None:
    truth = (0.1, 0.04)  # the beacon 10 cm ahead of the centre and 4 cm to the left; the configuration says (0, 0)
    robot = sim_config(ips_offset_m=truth)
    fitted_on, held_out = (_undeclared(simulated(robot, seed, loops=1, scenario="random")) for seed in (1, 2))
    start = sim_config()
    result = tune([fitted_on], start, lever_arm=True)
    assert result.ips_offset is not None
    assert math.dist(result.ips_offset, truth) < 0.02, result.ips_offset
    assert any(change.startswith("robot.ips_offset_m: [0, 0] ->") for change in result.changes)
    tuned = dataclasses.replace(
        start, ekf=result.ekf, robot=dataclasses.replace(start.robot, ips_offset_m=result.ips_offset)
    )
    before, after = replay(held_out, start).metrics, replay(held_out, tuned).metrics
    assert before is not None
    assert after is not None
    ours, theirs = after["ekf"], before["ekf"]
    assert ours is not None
    assert theirs is not None
    assert ours.rmse_m < theirs.rmse_m / 3  # a lever arm not modelled is an error of its whole length
    assert "ips_offset_m: [" in yaml_snippet(result)


def test_a_robot_that_never_turned_leaves_the_lever_arm_as_declared_and_says_why() -> None:
    robot = sim_config(ips_offset_m=(0.1, 0.04))
    square = _undeclared(simulated(robot, 3, loops=1, scenario="square"))  # the paper's square: driven, never turned
    result = tune([square], sim_config(), lever_arm=True)
    assert result.ips_offset is None
    assert not any(change.startswith("robot.ips_offset_m") for change in result.changes)
    assert any("only turns show the beacon's lever arm" in note for note in result.notes)


def test_a_lever_arm_declared_right_is_left_as_it_is() -> None:
    robot = sim_config(ips_offset_m=(0.1, 0.04))
    result = tune([simulated(robot, 1, loops=1, scenario="random")], robot, lever_arm=True)  # declared right
    assert result.before[0].turned_rad >= math.pi / 2  # the robot turned: the lever arm was fitted, not skipped
    assert result.ips_offset is None
    assert not any(change.startswith("robot.ips_offset_m") for change in result.changes)


def test_without_the_lever_arm_fit_each_log_keeps_the_lever_arm_it_declares() -> None:
    off_centre = simulated(sim_config(ips_offset_m=(0.1, 0.04)), 1, loops=1, scenario="random")
    centred = simulated(sim_config(), 2, loops=1, scenario="random")
    start = sim_config()
    result = tune([off_centre, centred], start)
    assert result.ips_offset is None
    fitted = dataclasses.replace(result.ekf, odometry_scale=start.ekf.odometry_scale)  # `after` is before the scales
    for log, after in zip((off_centre, centred), result.after, strict=True):
        assert after == score(log, start, fitted)[0]  # replayed with its own meta.robot.ips_offset
