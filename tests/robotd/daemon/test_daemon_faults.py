"""Hardware going away under the running daemon: the beacon unplugged and back, pigpiod absent, pigpiod killed."""

from __future__ import annotations

import contextlib
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest
from daemon_support import robot_config, running_robot, wait_until

from drivers.pigpiod.client import stop_pigpio_client
from robotd.kinematics import Twist

pytestmark = pytest.mark.slow


def test_the_beacon_unplugged_and_plugged_back_in_goes_stale_then_fusion_resumes(tmp_path: Path) -> None:
    overrides = {"pose_socket": {"status_rate_hz": 5.0}, "sim": {"ips_outage_rate_per_min": 0.0}}
    with running_robot(tmp_path, overrides) as robot:
        tap = robot.tap
        assert tap is not None
        wait_until(lambda: tap.pose["fix_state"] == "tracking", 5.0, "fixes before the unplug")
        robot.signal_vhw(signal.SIGUSR1)
        unplugged = time.monotonic()
        wait_until(
            lambda: (
                tap.statuses[-1]["t"] > unplugged
                and not tap.statuses[-1]["drivers"]["marvelmind"]["connected"]
                and tap.statuses[-1]["drivers"]["marvelmind"]["stale"]
            ),
            2.0,
            "the status to say the beacon is gone and its fix stale",
        )
        lost = tap.statuses[-1]
        wait_until(lambda: tap.pose["fix_state"] == "stale", 1.0, "the pose to say the fix is stale")
        fixes_while_out = lost["filter"]["fixes_accepted"]
        time.sleep(0.5)  # out for a while: no fix can arrive
        robot.signal_vhw(signal.SIGUSR2)
        plugged = time.monotonic()
        wait_until(
            lambda: tap.poses[-1][0] > plugged and tap.pose["fix_state"] == "tracking",
            robot.config.marvelmind.reconnect_max_s + 3.0,
            "fusion to resume",
        )
        back = tap.status_after(time.monotonic())
        marvelmind = back["drivers"]["marvelmind"]
        assert marvelmind["connected"]
        assert not marvelmind["stale"]
        assert back["filter"]["fixes_accepted"] > fixes_while_out, "no fix accepted after the beacon came back"
        assert "marvelmind: streaming from" in robot.daemon_log().split("vanished")[-1]
        assert robot.daemon is not None
        assert robot.daemon.poll() is None


def test_pigpiod_absent_at_start_is_a_clear_error_and_a_non_zero_exit(tmp_path: Path) -> None:
    config = robot_config(tmp_path)  # nobody listens on its pigpiod port: no vhw was started
    started = time.monotonic()
    result = subprocess.run(
        [sys.executable, "-m", "robotd", "run", "--config", str(config)],
        capture_output=True,
        text=True,
        timeout=20.0,
        check=False,
    )
    assert result.returncode != 0
    assert time.monotonic() - started < 10.0
    assert "pigpiod is not reachable" in result.stderr, result.stderr
    assert "Traceback" not in result.stderr, result.stderr
    assert not (tmp_path / "pose.sock").exists(), "the pose socket was left behind"


@dataclass
class CrashRun:
    """What a run whose virtual pigpiod was killed mid-motion and restarted left behind."""

    daemon_log: str
    motor_failures: int


@pytest.fixture(scope="module")
def crash_run(tmp_path_factory: pytest.TempPathFactory) -> CrashRun:
    """Drive, kill the vhw (pigpiod and beacon vanish at once), restart it; check the daemon's behaviour on the way."""
    # A long deadman, so the command sent before the crash would still be in force after the reconnection.
    # A short reconnection backoff cap, so the encoders' next attempt after the restart comes within the wait below.
    overrides = {
        "teleop": {"deadman_timeout_s": 5.0},
        "pose_socket": {"status_rate_hz": 5.0},
        "pigpiod": {"reconnect_max_s": 1.0},
    }
    with running_robot(tmp_path_factory.mktemp("crash"), overrides) as robot:
        tap = robot.tap
        assert tap is not None
        assert robot.vhw is not None
        assert robot.daemon is not None
        robot.drive(Twist(0.2, 0.0, 0.0), 0.5)
        assert any(robot.duties()), "the robot was not driving"
        robot.vhw.kill()
        robot.vhw.wait()
        with contextlib.suppress(OSError):  # the client library trips over its own dead socket
            stop_pigpio_client(robot.pi)
        wait_until(lambda: "reconnecting to pigpiod" in robot.daemon_log(), 2.0, "the daemon to notice")
        assert robot.daemon.poll() is None, robot.logs()
        robot.pi = None
        robot.start_vhw()  # pigpiod back on the same port (a fresh virtual robot, duties zero)
        wait_until(lambda: "motor outputs reconnected" in robot.daemon_log(), 5.0, "the motors to reconnect")
        reconnected = time.monotonic()
        # The last command arrived before the crash: it is still within the deadman timeout, but must not drive.
        while time.monotonic() < reconnected + 0.5:
            assert robot.duties() == (0.0, 0.0, 0.0, 0.0), "the motors drove on a command from before the crash"
            time.sleep(0.02)
        # the newest status, not the first after the reconnection: the encoders may come back a few statuses later
        wait_until(lambda: tap.statuses[-1]["drivers"]["encoders"]["reconnects"] >= 1, 5.0, "the encoders to reconnect")
        robot.send(Twist(0.2, 0.0, 0.0))  # a fresh command drives again
        wait_until(lambda: any(robot.duties()), 1.0, "the motors to drive on a fresh command")
        status = tap.status_after(time.monotonic())
        assert robot.daemon.poll() is None
        return CrashRun(robot.daemon_log(), status["drivers"]["control"]["motor_failures"])


def test_pigpiod_killed_during_a_run_the_daemon_reconnects_and_drives_only_after_a_fresh_command(
    crash_run: CrashRun,
) -> None:
    assert crash_run.motor_failures >= 1
    assert "robotd stopping after a failure" not in crash_run.daemon_log


def test_pigpiod_killed_during_a_run_leaves_no_tracebacks_in_the_daemons_log(crash_run: CrashRun) -> None:
    assert "Traceback" not in crash_run.daemon_log
