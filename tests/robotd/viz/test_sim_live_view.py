"""`robotd sim` serves the live view: a Foxglove client connects to the daemon of the virtual robot (real processes)
and sees its pose and frame tree; the pose agrees with the pose socket."""

from __future__ import annotations

import asyncio
import json
import os
import re
import signal
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from foxglove_client import FoxgloveClient
from process_support import processes_mentioning, start_sim, wait_for_output

pytestmark = pytest.mark.slow


@pytest.fixture
def out() -> Iterator[Path]:
    """The sim's folder, on a short path (its pose socket's path must fit in 108 bytes)."""
    with tempfile.TemporaryDirectory(prefix="rv-", dir="/tmp") as name:
        yield Path(name) / "sim"
        for pid in processes_mentioning(name):
            os.kill(pid, signal.SIGKILL)


async def read_poses(path: Path, into: dict[float, dict[str, Any]]) -> None:
    """Every pose of the pose socket, by its time t, until cancelled."""
    reader, writer = await asyncio.open_unix_connection(str(path))
    try:
        while True:
            message = json.loads(await reader.readline())
            if message["type"] == "pose":
                into[message["t"]] = message
    finally:
        writer.close()


async def test_a_foxglove_client_watches_the_virtual_robot_through_robotd_sim(out: Path) -> None:
    proc, output = start_sim(out)
    poses: dict[float, dict[str, Any]] = {}
    try:
        wait_for_output(proc, output, "Ctrl-C stops both.")
        match = re.search(r"live view: +ws://127\.0\.0\.1:(\d+)", output.read_text())
        assert match, output.read_text()
        reading = asyncio.create_task(read_poses(out / "pose.sock", poses))
        client = await FoxgloveClient.open(int(match.group(1)))
        try:
            await client.subscribe(["/pose/odometry", "/tf", "/daemon/status"])
            # two statuses: the first may have been made before the subscription it is delivered on (the viewer
            # publishes what came in the last 40 ms at once)
            got = await client.collect({"/pose/odometry": 20, "/tf": 5, "/daemon/status": 2}, timeout_s=30.0)
        finally:
            await client.close()
            reading.cancel()
    finally:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(60) == 0, output.read_text()
    status = got["/daemon/status"][-1].message
    assert status["drivers"]["viewer"]["subscriptions"] >= 1
    matched = 0
    for received in got["/pose/odometry"]:
        odometry = received.message
        pose = poses.get(float({kv.key: kv.value for kv in odometry.metadata}["t"]))
        if pose is None:
            continue
        matched += 1
        assert odometry.pose.position.x == pose["x"]
        assert odometry.pose.position.y == pose["y"]
        assert odometry.pose_covariance[0] == pose["covariance"][0]
        assert odometry.pose_covariance[6 * 5 + 5] == pose["covariance"][8]
    assert matched >= 5, f"only {matched} poses of the live view matched the pose socket's"
    daemon_log = (out / "daemon.log").read_text()
    assert "Traceback" not in daemon_log, daemon_log
