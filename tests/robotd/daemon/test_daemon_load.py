"""The daemon under abuse: a pose client that never reads, and a flood of hostile teleop datagrams (real processes).

Functional checks only: these tests must hold on a loaded machine. How well the control period holds meanwhile is a
figure of `robotd bench daemon`, not a pass/fail test.
"""

from __future__ import annotations

import random
import socket
import time
from collections.abc import Iterator

import pytest
from daemon_support import Robot, running_robot, wait_until

from robotd.bench.daemon import flood, hostile_datagrams, udp_queue

pytestmark = pytest.mark.slow

POSE_RATE_HZ = 500.0  # ~150 kB/s of pose lines: a client that never reads fills its socket buffer in about a second
STALL_S = 3.0
FLOOD_COUNT = 20_000


@pytest.fixture(scope="module")
def robot(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Robot]:
    """One virtual robot and daemon at rest, with a fast pose stream and 5 status messages a second."""
    overrides = {
        "pose_socket": {"rate_hz": POSE_RATE_HZ, "status_rate_hz": 5.0, "client_stall_s": STALL_S},
        # every hostile datagram parsed and counted by its reason: no per-source limit, no read budget
        "teleop": {"max_datagrams_per_s": 1e6, "read_budget_per_s": 1e7},
    }
    with running_robot(tmp_path_factory.mktemp("load"), overrides) as robot:
        yield robot


def test_a_pose_client_that_never_reads_is_cut_off_and_nobody_else_waits_for_it(robot: Robot) -> None:
    assert robot.tap is not None
    before = robot.tap.status_after(time.monotonic())
    pose_socket_before = before["drivers"]["pose_socket"]
    stuck = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        stuck.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        stuck.connect(robot.config.pose_socket.path)
        connected = time.monotonic()
        # The stuck client's queue overflows once its socket is full: from then on it is truly stuck.
        full = robot.tap.status_after(connected)
        while full["drivers"]["pose_socket"]["dropped_messages"] == pose_socket_before["dropped_messages"]:
            full = robot.tap.status_after(full["t"])
        poses_when_full = len(robot.tap.poses)
        during = robot.tap.status_after(full["t"])
        # Meanwhile the control loop steps and the well-behaved client keeps receiving poses.
        assert during["drivers"]["control"]["control_steps"] > full["drivers"]["control"]["control_steps"]
        wait_until(lambda: len(robot.tap.poses) > poses_when_full + 10, STALL_S, "poses for the other client")  # type: ignore[union-attr]
        # And the daemon ends it: a client that accepts nothing for client_stall_s is disconnected.
        wait_until(
            lambda: (
                robot.tap is not None
                and robot.tap.statuses[-1]["drivers"]["pose_socket"]["stalled"] == pose_socket_before["stalled"] + 1
            ),
            STALL_S + 10.0,
            "the stuck client to be disconnected",
        )
        assert robot.daemon is not None
        assert robot.daemon.poll() is None
    finally:
        stuck.close()


def test_a_flood_of_hostile_datagrams_is_rejected_one_by_one_and_nothing_drives(robot: Robot) -> None:
    assert robot.tap is not None
    assert robot.daemon is not None
    port = robot.config.teleop.port
    before = robot.tap.status_after(time.monotonic())
    _queued, drops_before = udp_queue(port)
    sent = flood(port, hostile_datagrams(random.Random(11), FLOOD_COUNT))
    wait_until(lambda: udp_queue(port)[0] == 0, 30.0, "the daemon to read every datagram")
    after = robot.tap.status_after(time.monotonic())
    assert robot.daemon.poll() is None, robot.logs()
    kernel_drops = udp_queue(port)[1] - drops_before  # none expected (the flood waits on the queue), but not a bug
    teleop_before, teleop_after = before["drivers"]["teleop"], after["drivers"]["teleop"]
    counts = {k for k in teleop_after if k not in ("accepted", "answered", "read_pauses")}
    rejected = {k: teleop_after[k] - teleop_before[k] for k in counts}
    assert teleop_after["accepted"] == teleop_before["accepted"], "a hostile datagram was taken as a command"
    # every datagram the daemon read is rejected and counted, by reason (a rate limit, where there is one, counts too)
    assert sum(rejected.values()) + kernel_drops == sent == FLOOD_COUNT
    by_reason = {k for k, n in rejected.items() if n}
    assert "rate_limited" in by_reason or by_reason >= {
        "oversized", "malformed", "version", "bad_tag", "non_finite", "clock_offset",
    }  # fmt: skip
    assert after["drivers"]["control"]["control_steps"] > before["drivers"]["control"]["control_steps"]
    assert after["drivers"]["control"]["state"] in {"deadman", "idle"}
    assert robot.duties() == (0.0, 0.0, 0.0, 0.0)
    assert "Traceback" not in robot.daemon_log()
