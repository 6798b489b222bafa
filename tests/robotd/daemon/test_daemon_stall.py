"""A dead encoder on the virtual robot: the daemon stops the wheels instead of winding the PID up (real processes)."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
import yaml
from daemon_support import Robot, wait_until

from robotd.kinematics import Twist

pytestmark = pytest.mark.slow

FREE_GPIOS = {"a": 9, "b": 10}  # wired to nothing on the virtual robot: no edge ever arrives


def test_an_unplugged_encoder_stops_the_robot_holds_the_fault_and_a_fresh_command_clears_it(tmp_path: Path) -> None:
    robot = Robot(tmp_path, {"pose_socket": {"status_rate_hz": 5.0}})
    try:
        robot.start_vhw()
        # The daemon reads the front-left encoder on pins the virtual robot does not drive: its wire is cut.
        raw = yaml.safe_load(robot.config_path.read_text(encoding="utf-8"))
        raw["encoders"] = {"wheels": {"front_left": FREE_GPIOS}}  # config/sim.yaml has the default wiring
        robot.config_path = tmp_path / "daemon.yaml"
        robot.config_path.write_text(yaml.safe_dump(raw), encoding="utf-8")
        robot.start_daemon()
        tap = robot.tap
        assert tap is not None

        def faults() -> list[dict[str, object]]:
            found: list[dict[str, object]] = tap.statuses[-1]["drivers"]["control"]["faults"] if tap.statuses else []
            return found

        # The case: a held 0.1 m/s command. The wheels turn, then the guard stops them all.
        started = time.monotonic()
        while not faults() and time.monotonic() < started + 15.0:
            robot.drive(Twist(0.1, 0.0, 0.0), 0.2)
        assert faults(), robot.logs()
        assert faults()[0]["wheels"] == ["front_left"]
        robot.drive(Twist(0.1, 0.0, 0.0), 0.5)  # the same command held on: the motors stay off
        assert robot.duties() == (0.0, 0.0, 0.0, 0.0)
        assert robot.daemon_log().count("WARNING: control: front_left driven hard but not turning") == 1
        # Let go, then command again: the fault clears and the wheels drive.
        robot.send(Twist(0.0, 0.0, 0.0))
        held = tap.status_after(time.monotonic() + 0.1)
        assert held["drivers"]["control"]["faults"], "the fault holds until a fresh command"
        robot.send(Twist(0.1, 0.0, 0.0))
        wait_until(lambda: any(robot.duties()), 2.0, "the motors to drive on a fresh command")
        assert "INFO: control: stall fault cleared by a fresh command" in robot.daemon_log()
        robot.send(Twist(0.0, 0.0, 0.0))
        assert robot.daemon is not None
        assert robot.daemon.poll() is None
        assert "Traceback" not in robot.daemon_log()
    finally:
        robot.close()
