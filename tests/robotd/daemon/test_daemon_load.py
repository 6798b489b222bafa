"""The daemon under abuse: a pose client that never reads, and a flood of hostile teleop datagrams."""

from __future__ import annotations

import random
import socket
import time
from collections.abc import Iterator
from typing import Any

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


def period(status: dict[str, Any]) -> dict[str, float]:
    """The control loop's period statistics (ms) over the second before a status message."""
    stats: dict[str, float] = status["drivers"]["control"]["period"]
    return stats


def assert_on_schedule(stats: dict[str, float], nominal_ms: float, what: str) -> None:
    """The control period held: the median on the nominal period, no tick more than 5 ms late."""
    assert stats["ticks"] >= 0.9 * 1000.0 / nominal_ms, f"{what}: too few control ticks in a second: {stats}"
    assert stats["p50_ms"] == pytest.approx(nominal_ms, abs=1.0), f"{what}: {stats}"
    assert stats["p99_ms"] < nominal_ms + 5.0, f"{what}: {stats}"


def test_a_pose_client_that_never_reads_does_not_change_the_control_period(robot: Robot) -> None:
    assert robot.tap is not None
    nominal_ms = 1000.0 / robot.config.control.rate_hz
    before = robot.tap.status_after(robot.tap.poses[0][0] + 1.1)  # a full window of ticks
    assert_on_schedule(period(before), nominal_ms, "before")
    stuck = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        stuck.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        stuck.connect(robot.config.pose_socket.path)
        connected = time.monotonic()
        # The stuck client's queue overflows once its socket is full: from then on it is truly stuck.
        drops = before["drivers"]["pose_socket"]["dropped_messages"]
        full = robot.tap.status_after(connected)
        while full["drivers"]["pose_socket"]["dropped_messages"] == drops:
            full = robot.tap.status_after(full["t"])
        during = robot.tap.status_after(full["t"] + 1.0)  # its period window lies wholly in the stuck time
        assert during["drivers"]["pose_socket"]["stalled"] == before["drivers"]["pose_socket"]["stalled"]
        assert during["t"] < connected + STALL_S, "the stuck client was cut off before the measurement"
        assert_on_schedule(period(during), nominal_ms, "with a stuck client")
        # Meanwhile the well-behaved client keeps receiving poses at the full rate.
        recent = [arrived for arrived, _ in robot.tap.poses if during["t"] - 1.0 < arrived <= during["t"]]
        assert len(recent) > 0.8 * POSE_RATE_HZ
        # And the daemon ends it: a client that accepts nothing for client_stall_s is disconnected.
        wait_until(
            lambda: (
                robot.tap is not None
                and robot.tap.statuses[-1]["drivers"]["pose_socket"]["stalled"]
                == before["drivers"]["pose_socket"]["stalled"] + 1
            ),
            STALL_S + 2.0,
            "the stuck client to be disconnected",
        )
    finally:
        stuck.close()


def test_a_flood_of_hostile_datagrams_is_rejected_one_by_one_and_leaves_the_daemon_and_its_period_alone(
    robot: Robot,
) -> None:
    assert robot.tap is not None
    assert robot.daemon is not None
    port = robot.config.teleop.port
    # a full window of control ticks before the flood: a status less than a second after start-up counts fewer
    before = robot.tap.status_after(max(time.monotonic(), robot.tap.poses[0][0] + 1.1))
    _queued, drops_before = udp_queue(port)
    started = time.monotonic()
    sent = flood(port, hostile_datagrams(random.Random(11), FLOOD_COUNT))
    flooded = time.monotonic()
    wait_until(lambda: udp_queue(port)[0] == 0, 5.0, "the daemon to read every datagram")
    after = robot.tap.status_after(time.monotonic())
    assert robot.daemon.poll() is None, robot.logs()
    assert udp_queue(port)[1] == drops_before, "the kernel dropped datagrams: the count below would be short"
    teleop_before, teleop_after = before["drivers"]["teleop"], after["drivers"]["teleop"]
    counts = {k for k in teleop_after if k not in ("accepted", "answered", "read_pauses")}
    rejected = {k: teleop_after[k] - teleop_before[k] for k in counts}
    assert teleop_after["accepted"] == teleop_before["accepted"], "a hostile datagram was taken as a command"
    assert sum(rejected.values()) == sent == FLOOD_COUNT
    assert {k for k, n in rejected.items() if n} >= {
        "oversized", "malformed", "version", "bad_tag", "non_finite", "clock_offset",
    }  # fmt: skip
    # The flood lasted about a second at most: the status stamped during or just after it covers it.
    nominal_ms = 1000.0 / robot.config.control.rate_hz
    covering = [s for s in robot.tap.statuses if started + 0.2 < s["t"] <= flooded + 1.0]
    assert covering, "no status message during the flood"
    for status in covering:
        assert_on_schedule(period(status), nominal_ms, f"during the flood ({flooded - started:.2f} s)")
    assert robot.duties() == (0.0, 0.0, 0.0, 0.0)
    assert "Traceback" not in robot.daemon_log()
