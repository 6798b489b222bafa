"""`robotd fleet view`: two in-process daemons on a real mosquitto, the view from the broker, a real Foxglove client."""

from __future__ import annotations

import asyncio
import contextlib
import math
import shlex
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import foxglove
import pytest
from fleet_support import FleetDaemon, watcher
from foxglove_client import FoxgloveClient, Received
from inprocess_daemon import FakeEncoders, running, until

from drivers.wheels.encoders import WheelTicks
from robotd.cli import build_parser, main
from robotd.commands.fleet import run_view
from robotd.fleet import topics
from robotd.fleet.broker import OPERATOR, Broker
from robotd.fleet.fleet_scene import ALARM_COLOUR, OFFLINE_COLOUR, FleetScene, label_of, status_summary
from robotd.fleet.operator import BrokerAddress
from robotd.fleet.secrets import load_credentials
from robotd.fleet.view import ViewServer, serve_fleet_view
from robotd.tools.fleet_sim import VirtualFleet, how_to_watch
from robotd.viz import scene

ROBOT_TOPICS = ("pose", "pose/ellipse", "pose/trail", "status", "label")


@contextlib.asynccontextmanager
async def fleet_view(broker: Broker) -> AsyncIterator[tuple[int, asyncio.Task[FleetScene]]]:
    """The view of `broker` as its operator, on a free loopback port: (port, its task)."""
    setup = broker.setup
    credentials = load_credentials(str(setup.credentials_file(OPERATOR)), "--credentials")
    ready: asyncio.Future[int] = asyncio.get_running_loop().create_future()
    task = asyncio.create_task(
        serve_fleet_view(BrokerAddress.parse(setup.url), credentials, ViewServer(port=0), on_ready=ready.set_result)
    )
    try:
        port = await asyncio.wait_for(ready, 10.0)
        yield port, task
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


class TurningEncoders(FakeEncoders):
    """FakeEncoders whose counts follow the speeds (so that odometry moves the pose), at 6800 counts a turn."""

    COUNTS_PER_RAD = 6800 / math.tau

    def __init__(self, speeds: tuple[float, float, float, float]) -> None:
        super().__init__(time.monotonic)
        self.speeds = list(speeds)
        self.started = time.monotonic()

    def ticks(self, degraded: bool = False) -> WheelTicks:
        """The counts of turning at the set speeds since the start."""
        t = self.clock()
        a, b, c, d = (round(speed * (t - self.started) * self.COUNTS_PER_RAD) for speed in self.speeds)
        return WheelTicks(t, (a, b, c, d), (self.speeds[0], self.speeds[1], self.speeds[2], self.speeds[3]), degraded)


def drive(robot: FleetDaemon, speeds: tuple[float, float, float, float]) -> None:
    """Turn the robot's wheels (rad/s each: FL, FR, RL, RR), so that its pose moves."""
    robot.daemon.encoders = TurningEncoders(speeds)


def on(received: dict[str, list[Received]], topic: str) -> list[Any]:
    return [item.message for item in received.get(topic, [])]


async def test_the_view_shows_each_robot_as_it_publishes_and_its_last_word(
    tmp_path: Path, broker: Broker, fleet_key: tuple[Path, bytes]
) -> None:
    r1, r2 = (FleetDaemon(tmp_path / name, broker, name, fleet_key[0]) for name in ("r1", "r2"))
    drive(r1, (4.0, 4.0, 4.0, 4.0))  # forward
    drive(r2, (-3.0, 3.0, -3.0, 3.0))  # turning on the spot
    async with fleet_view(broker) as (port, view), watcher(broker) as watching:
        client = await FoxgloveClient.open(port)  # before any robot: each appears when it first speaks
        try:
            async with running(r1.daemon):
                async with running(r2.daemon):
                    await client.wait_for_topics({f"/{r}/{leaf}" for r in ("r1", "r2") for leaf in ROBOT_TOPICS})
                    subscribed = [f"/{r}/{leaf}" for r in ("r1", "r2") for leaf in ROBOT_TOPICS]
                    await client.subscribe([*subscribed, "/tf"])
                    received = await client.collect(
                        {"/r1/pose": 10, "/r2/pose": 10, "/r1/status": 1, "/r1/label": 1, "/tf": 20}
                    )
                # r2's link ends (a clean exit: `offline` as the last will would say)
                offline: list[Any] = []
                labels: list[str] = []
                while "r2 offline" not in labels:
                    item = await client.receive()
                    if item.topic == "/r2/status":
                        offline.append(item.message)
                    elif item.topic == "/r2/label":
                        labels.extend(entity.texts[0].text for entity in item.message.entities)
        finally:
            await client.close()
        assert not view.done()
    for name in ("r1", "r2"):
        published = [(p["x"], p["y"], p["theta"]) for p in watching.on(topics.pose(name))]
        shown = on(received, f"/{name}/pose")
        assert shown
        assert all(pose.frame_id == "map" for pose in shown)
        for pose in shown:
            position, orientation = pose.pose.position, pose.pose.orientation
            assert any(
                (x, y) == (position.x, position.y) and math.isclose(orientation.z, math.sin(0.5 * th), abs_tol=1e-12)
                for x, y, th in published
            ), f"{name}: a pose in the view that it never published"
        assert len({(p.pose.position.x, p.pose.orientation.z) for p in shown}) > 1, f"{name} did not move"
    frames = {t.child_frame_id: t for message in on(received, "/tf") for t in message.transforms}
    assert set(frames) == {"r1/base_link", "r2/base_link"}
    assert all(t.parent_frame_id == "map" for t in frames.values())
    r1_positions = {(p["x"], p["y"]) for p in watching.on(topics.pose("r1"))}
    assert (frames["r1/base_link"].translation.x, frames["r1/base_link"].translation.y) in r1_positions
    assert all(e.entities[0].frame_id == "map" and e.entities[0].lines for e in on(received, "/r1/pose/ellipse"))
    status = on(received, "/r1/status")[-1]
    assert (status["state"], status["online"], status["stop_held"], status["robot_id"]) == ("online", True, False, "r1")
    assert status["status"]["robot_id"] == "r1"
    assert (offline[-1]["state"], offline[-1]["online"]) == ("offline", False)
    (r1_label,) = on(received, "/r1/label")[-1].entities
    assert (r1_label.frame_id, r1_label.texts[0].text) == ("r1/base_link", "r1")


def test_the_command_says_when_the_broker_cannot_be_reached(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["fleet", "view", "--broker", "mqtt://127.0.0.1:1", "--port", "0", "--for", "5"]) == 1
    error = capsys.readouterr().err
    assert error.startswith("robotd fleet view: broker mqtt://127.0.0.1:1:")
    assert len(error.strip().splitlines()) == 1


def test_the_virtual_fleet_says_how_to_open_the_view(tmp_path: Path) -> None:
    fleet = VirtualFleet(
        "mqtt://127.0.0.1:41234",
        tmp_path / "operator.credentials",
        tmp_path / "fleet.key",
        ("r1", "r2"),
        (),
        None,  # type: ignore[arg-type]
    )
    lines = [line for line in how_to_watch(fleet, tmp_path).splitlines() if "robotd fleet view" in line]
    assert len(lines) == 1
    command = shlex.split(lines[0].split(":", 1)[1].split("(")[0])
    args = build_parser().parse_args(command[1:])
    assert args.handler is run_view
    assert (args.broker, args.credentials) == ("mqtt://127.0.0.1:41234", str(tmp_path / "operator.credentials"))


def test_bad_messages_are_counted_and_draw_nothing() -> None:
    fleet = FleetScene(foxglove.Context())
    fleet.take(topics.pose("r1"), b"not json")
    fleet.take(topics.pose("r1"), b"[1, 2]")
    fleet.take(topics.pose("r1"), b'{"x": 1.0, "y": "two", "theta": 0.0, "covariance": [0, 0, 0, 0, 0, 0, 0, 0, 0]}')
    fleet.take(topics.pose("r1"), b'{"x": NaN, "y": 0.0, "theta": 0.0, "covariance": [0, 0, 0, 0, 0, 0, 0, 0, 0]}')
    fleet.take(topics.FLEET_STOP, b'{"action": "stop"}')  # an order: not a robot
    fleet.take(topics.status("r2"), b"")  # a deleted retained status
    assert (fleet.malformed, fleet.skipped, fleet.messages) == (2, 2, 0)
    assert fleet.robots == {}
    fleet.take(topics.pose("r1"), b'{"x": 1.0, "y": 2.0, "theta": 0.5, "covariance": [1, 0, 0, 0, 1, 0, 0, 0, 1]}')
    assert (fleet.messages, list(fleet.robots)) == (1, ["r1"])


async def test_the_view_keeps_serving_through_a_broker_outage_and_follows_again(
    tmp_path: Path, broker: Broker, fleet_key: tuple[Path, bytes], capsys: pytest.CaptureFixture[str]
) -> None:
    robot = FleetDaemon(tmp_path / "r1", broker, "r1", fleet_key[0], reconnect_max_s=0.2)
    drive(robot, (4.0, 4.0, 4.0, 4.0))
    async with fleet_view(broker) as (port, view), running(robot.daemon):
        client = await FoxgloveClient.open(port)
        try:
            await client.subscribe(["/r1/pose"])
            await client.collect({"/r1/pose": 3})
            await asyncio.to_thread(broker.stop)
            await until(lambda: "retrying in" in capsys.readouterr().err, "the view to say the broker is away")
            with contextlib.suppress(TimeoutError):  # what the view published before the outage, read and dropped
                while True:
                    await client.receive(timeout_s=1.0)
            await asyncio.to_thread(broker.start)
            await until(lambda: robot.fleet.connected, "the robot back on the broker", 20.0)
            await client.collect({"/r1/pose": 3}, timeout_s=30.0)  # new poses, on the same connection to the view
        finally:
            await client.close()
        assert not view.done()


def test_a_label_says_what_is_wrong() -> None:
    online = {"state": "online", "robot_id": "r1", "stop": {"held": True}, "faults": [{"kind": "stall"}]}
    assert label_of(status_summary("r1", online)) == ("r1 STOP stall", ALARM_COLOUR)
    assert label_of(status_summary("r1", {"state": "online"})) == ("r1", scene.FUSED_COLOUR)
    assert label_of(status_summary("r1", {"state": "offline", "robot_id": "r1"})) == ("r1 offline", OFFLINE_COLOUR)


def test_the_command_says_where_to_connect(broker: Broker, capsys: pytest.CaptureFixture[str]) -> None:
    setup = broker.setup
    credentials = str(setup.credentials_file(OPERATOR))
    argv = ["fleet", "view", "--broker", setup.url, "--credentials", credentials, "--port", "0", "--for", "0.5"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"robotd fleet view: {setup.url} served on ws://127.0.0.1:")
    assert int(out.split("ws://127.0.0.1:")[1].split()[0]) > 0  # the free port the server took, not 0
