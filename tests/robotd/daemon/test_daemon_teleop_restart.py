"""Teleop across a daemon restart (real processes): a capture replayed is refused, the real client re-syncs."""

from __future__ import annotations

import socket
import time
from pathlib import Path
from typing import Any

import pytest
from daemon_support import Robot, running_robot, wait_until

from robotd.kinematics import Twist
from robotd.tools.teleop_client import UdpLink

pytestmark = pytest.mark.slow

RATE_HZ = 20.0


def teleop_counters(robot: Robot) -> dict[str, Any]:
    """The daemon's teleop counters from its next status message."""
    assert robot.tap is not None
    counters: dict[str, Any] = robot.tap.status_after(time.monotonic())["drivers"]["teleop"]
    return counters


def test_a_capture_replayed_after_a_restart_is_refused_and_the_client_drives_again(tmp_path: Path) -> None:
    # the clock check is made lenient so that only the instance can refuse the capture (the finding)
    overrides = {"teleop": {"max_clock_offset_s": 60.0}, "pose_socket": {"status_rate_hz": 5.0}}
    with running_robot(tmp_path, overrides) as robot:
        port = robot.config.teleop.port
        client = UdpLink("127.0.0.1", port, None)
        try:
            assert client.sync(5.0)
            # an eavesdropper captures 20 datagrams of a session that drives the robot
            capture = []
            for _ in range(20):
                capture.append(client.sender.command(Twist(0.3, 0.0, 0.0), time.time()))
                client.sock.send(capture[-1])
                time.sleep(1.0 / RATE_HZ)
            assert any(robot.duties()), "the captured commands did not drive"
            wait_until(lambda: not any(robot.duties()), 5.0, "the deadman to stop the robot")

            assert robot.daemon is not None
            assert robot.tap is not None
            robot.tap.close()
            assert robot.children.stop(robot.daemon) == 0
            robot.start_daemon()

            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as attacker:
                attacker.connect(("127.0.0.1", port))
                for datagram in capture:
                    attacker.send(datagram)
                    time.sleep(1.0 / RATE_HZ)
                    assert not any(robot.duties()), "a replayed datagram drove the motors"
            counters = teleop_counters(robot)
            assert counters["stale_session"] == 20
            assert counters["accepted"] == 0

            # the real client carries on at its rate: answered once, it drives the restarted daemon
            deadline = time.monotonic() + 5.0
            while not any(robot.duties()) and time.monotonic() < deadline:
                client.send(Twist(0.3, 0.0, 0.0))
                time.sleep(1.0 / RATE_HZ)
            assert any(robot.duties()), "the client did not drive the restarted daemon"
            assert client.resyncs == 2
            client.send(Twist(0.0, 0.0, 0.0))
        finally:
            client.sock.close()
