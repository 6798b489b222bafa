"""The live view: a real WebSocket client speaking Foxglove's protocol watches the in-process daemon (real sockets on
loopback, the real SDK server), and what it decodes is what the pose socket says."""

from __future__ import annotations

import asyncio
import itertools
import json
import math
import time
from pathlib import Path
from typing import Any

from foxglove_client import FoxgloveClient
from inprocess_daemon import FakeEncoders, FakeMotors, daemon_config, running, until
from viz_support import RollingEncoders, fix

from drivers.marvelmind.events import StationaryBeacon, StationaryBeacons
from robotd.daemon.service import Daemon


def yaw(q: Any) -> float:
    """The heading of a quaternion about z."""
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


async def read_poses(path: Path, into: dict[float, dict[str, Any]], stop: asyncio.Event) -> None:
    """Every pose message of the pose socket, by its time t."""
    reader, writer = await asyncio.open_unix_connection(str(path))
    try:
        while not stop.is_set():
            line = await reader.readline()
            message = json.loads(line)
            if message["type"] == "pose":
                into[message["t"]] = message
    finally:
        writer.close()


def start_daemon(tmp_path: Path) -> Daemon:
    config = daemon_config(tmp_path, viewer={"enabled": True, "port": 0}, pose_socket={"rate_hz": 20.0})
    return Daemon(config, encoders=RollingEncoders(time.monotonic), motors_factory=FakeMotors)


async def connect_viewer(daemon: Daemon) -> FoxgloveClient:
    """A Foxglove client connected to the running daemon's live view, once its server is up."""
    await until(lambda: daemon.viewer is not None and daemon.viewer.port is not None, "the live view's server")
    assert daemon.viewer is not None
    assert daemon.viewer.port is not None
    return await FoxgloveClient.open(daemon.viewer.port)


async def test_a_foxglove_client_sees_the_pose_and_covariance_the_pose_socket_sends(tmp_path: Path) -> None:
    daemon = start_daemon(tmp_path)
    async with running(daemon):
        client = await connect_viewer(daemon)
        poses: dict[float, dict[str, Any]] = {}
        stop = asyncio.Event()
        await until((tmp_path / "pose.sock").exists, "the pose socket")
        reading = asyncio.create_task(read_poses(tmp_path / "pose.sock", poses, stop))
        try:
            await client.subscribe(["/pose/odometry", "/pose", "/tf", "/pose/ellipse", "/log/wheels", "/control"])
            got = await client.collect({"/pose/odometry": 20, "/pose": 20, "/tf": 5, "/log/wheels": 5, "/control": 5})
        finally:
            stop.set()
            await client.close()
            reading.cancel()
    assert client.server_info["name"] == "robotd"
    matched = 0
    for received in got["/pose/odometry"]:
        odometry = received.message
        t = float({kv.key: kv.value for kv in odometry.metadata}["t"])
        if t not in poses:
            continue  # published before the pose socket's client connected
        pose = poses[t]
        matched += 1
        assert odometry.frame_id == "map"
        assert odometry.body_frame_id == "base_link"
        assert odometry.pose.position.x == pose["x"]
        assert odometry.pose.position.y == pose["y"]
        assert math.isclose(yaw(odometry.pose.orientation), pose["theta"], abs_tol=1e-12)
        cov6 = list(odometry.pose_covariance)
        for i, row in enumerate((0, 1, 5)):
            for j, col in enumerate((0, 1, 5)):
                assert cov6[6 * row + col] == pose["covariance"][3 * i + j], (row, col)
    assert matched >= 5, f"only {matched} Foxglove poses matched a pose of the pose socket"
    xs = [r.message.pose.position.x for r in got["/pose"]]
    assert xs[-1] > xs[0], "the robot drove forward: the fused pose moves"
    assert {t.child_frame_id for r in got["/tf"] for t in r.message.transforms} == {"odom", "base_link", "beacon"}
    wheels = got["/log/wheels"][-1].message
    assert wheels["type"] == "wheels"
    assert len(wheels["ticks"]) == 4
    control = got["/control"][-1].message
    assert control["measured_rad_s"] == [2.0, 2.0, 2.0, 2.0]
    assert control["period_ms"] is not None


async def test_the_trail_holds_the_fused_poses_a_centimetre_apart_and_grows_as_the_robot_drives(
    tmp_path: Path,
) -> None:
    daemon = start_daemon(tmp_path)
    async with running(daemon):
        client = await connect_viewer(daemon)
        try:
            await client.subscribe(["/pose", "/pose/trail"])
            got = await client.collect({"/pose": 40, "/pose/trail": 3})
        finally:
            await client.close()
    trails = [r.message.poses for r in got["/pose/trail"]]
    assert all(r.message.frame_id == "map" for r in got["/pose/trail"])
    assert len(trails[-1]) > len(trails[0]) >= 1, "the robot drives: the trail grows"
    points = [(p.position.x, p.position.y, yaw(p.orientation)) for p in trails[-1]]
    for (x0, y0, th0), (x1, y1, th1) in itertools.pairwise(points):
        turned = abs(math.remainder(th1 - th0, math.tau))
        assert math.hypot(x1 - x0, y1 - y0) >= 0.01 or turned >= 0.05, "a pose is kept once the robot moved"
    fused = {(r.message.pose.position.x, r.message.pose.position.y) for r in got["/pose"]}
    kept = {(x, y) for x, y, _ in points}
    assert kept & fused, "the trail's poses are fused poses the viewer was sent"


async def test_fixes_are_drawn_coloured_by_verdict_and_beacons_appear_when_reported(tmp_path: Path) -> None:
    daemon = start_daemon(tmp_path)
    async with running(daemon):
        client = await connect_viewer(daemon)
        try:
            await client.subscribe(["/ips/fixes", "/ips/verdicts", "/beacons", "/daemon/log"])
            await asyncio.sleep(0.2)  # the subscription reaches the server before the fixes do
            for _ in range(4):
                fix(daemon, 0.0, 0.0)
                await asyncio.sleep(0.05)
            fix(daemon, 40.0, 40.0)  # far off: the gate rejects it
            now = daemon.clock()
            daemon._on_marvelmind(StationaryBeacons(now, (StationaryBeacon(2, 5.0, 1.0, 2.0),), 0x12))
            got = await client.collect({"/ips/verdicts": 5, "/ips/fixes": 5, "/beacons": 1})
        finally:
            await client.close()
    verdicts = [r.message["verdict"] for r in got["/ips/verdicts"]]
    assert "seeded" in verdicts, verdicts
    assert verdicts[-1] == "gated", verdicts
    gated = got["/ips/verdicts"][-1].message
    assert gated["nis"] > gated["gate"]
    assert not gated["accepted"]
    colours = {(round(e.spheres[0].color.r, 2), round(e.spheres[0].color.g, 2)) for r in got["/ips/fixes"]
               for e in r.message.entities}  # fmt: skip
    assert (0.95, 0.15) in colours, "the gated fix is drawn red"
    beacon = got["/beacons"][0].message.entities[0]
    assert beacon.id == "beacon-2"
    assert beacon.spheres[0].pose.position.x == 5.0


async def test_the_viewer_never_blocks_the_daemon_a_full_queue_drops_and_counts(tmp_path: Path) -> None:
    config = daemon_config(tmp_path, viewer={"enabled": True, "port": 0, "queue": 16})
    daemon = Daemon(config, encoders=FakeEncoders(lambda: 0.0), motors_factory=FakeMotors)
    viewer = daemon.viewer
    assert viewer is not None
    # not started: nothing takes items off the queue, as with a publishing thread that stalls
    for _ in range(100):
        viewer.status({"t": 1.0, "type": "status"})
    assert viewer.dropped == 100 - 16
    assert daemon._status_message(1.0)["drivers"]["viewer"]["dropped"] == 84


async def test_a_daemon_with_a_viewer_and_no_input_yet_publishes_without_a_fault(tmp_path: Path) -> None:
    """Before its first wheel tick or fix the daemon's estimate has no time; the view skips it rather than fail."""
    config = daemon_config(tmp_path, viewer={"enabled": True, "port": 0}, pose_socket={"rate_hz": 50.0})
    silent = FakeEncoders(time.monotonic, period_s=3600.0)  # no tick during the test
    daemon = Daemon(config, encoders=silent, motors_factory=FakeMotors)
    async with running(daemon):
        viewer = daemon.viewer
        assert viewer is not None
        await until(lambda: viewer.published > 0 and viewer.counters()["queued"] == 0, "the viewer publishing")
        await asyncio.sleep(0.3)  # several pose periods with no input at all
        assert silent.published == 0
        assert viewer.counters()["state"] == "running"
