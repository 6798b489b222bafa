"""The pose socket publishes the estimate at the publishing instant: extrapolated, its covariance grown with it."""

from __future__ import annotations

import asyncio
import json
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from inprocess_daemon import Harness, daemon_config

from drivers.marvelmind.events import Position


@pytest.fixture
def short_dir() -> Iterator[Path]:
    """A directory with a short path: a Unix socket path must fit in 108 bytes, pytest's tmp_path may not."""
    with tempfile.TemporaryDirectory(prefix="rd-", dir="/tmp") as name:
        yield Path(name)


async def _read_pose(reader: asyncio.StreamReader) -> dict[str, Any]:
    while True:
        message: dict[str, Any] = json.loads(await asyncio.wait_for(reader.readline(), 5.0))
        if "covariance" in message:
            return message


async def test_the_published_pose_is_the_estimate_at_the_daemon_s_clock_with_its_grown_covariance(
    short_dir: Path,
) -> None:
    harness = Harness(daemon_config(short_dir))
    daemon, clock = harness.daemon, harness.clock
    estimator = daemon.estimator
    start = clock.now
    for k in range(1, 401):  # 4 s at 0.3 m/s straight ahead (x), fixes at 8 Hz on the true path
        t = start + 0.01 * k
        estimator.on_twist(t, 0.3, 0.0, 0.0)
        if k % 12 == 0:
            estimator.on_fix(t, 0.3 * (t - start), 0.0, t)
    newest = estimator.pose()
    await daemon.pose_server.start()
    reader, writer = await asyncio.open_unix_connection(str(daemon.config.pose_socket.path))
    try:
        while daemon.pose_server.clients == 0:
            await asyncio.sleep(0.001)
        clock.now = newest.t + 0.5  # the pose task wakes half a second after the newest input
        daemon._publish_pose()
        pose = await _read_pose(reader)
    finally:
        writer.close()
        await writer.wait_closed()
        await daemon.pose_server.close()
    assert pose["t"] == clock.now
    assert abs(pose["x"] - (newest.x + 0.15)) < 1e-9  # 0.5 s further at the twist in force
    covariance = pose["covariance"]
    assert covariance[0] > newest.cov[0]  # along the motion: the process noise of 0.15 m of travel
    assert covariance[8] > newest.cov[8]  # the heading too (slip grows with distance)
    assert covariance[0] == estimator.pose(clock.now).cov[0]


def test_a_fix_s_pose_is_published_before_the_filter_learns_from_it_and_the_next_wheel_sample_settles_it(
    short_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    harness = Harness(daemon_config(short_dir))
    daemon, clock = harness.daemon, harness.clock
    calls: list[str] = []
    settle, publish = daemon.estimator.settle, daemon._publish_pose

    def recorded_settle() -> None:
        if daemon.estimator._unsettled is not None:  # a fix to learn from
            calls.append("learn")
        settle()

    def recorded_publish() -> None:
        calls.append("pose")
        publish()

    monkeypatch.setattr(daemon.estimator, "settle", recorded_settle)
    monkeypatch.setattr(daemon, "_publish_pose", recorded_publish)
    for _ in range(10):  # odometry from well before the fix was measured
        harness.tick()
    calls.clear()
    fix = Position(clock.now, clock.now - 0.05, 0.0, 0.0, 0.0, 5, 0, 0.0, 0, 0, 0.05, 0x11)
    daemon._on_marvelmind(fix)
    assert calls == ["pose"]
    harness.tick()
    assert calls == ["pose", "learn"]
