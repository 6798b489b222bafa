"""The fleet link in the real daemon (fake wheels) on a real mosquitto: poses, status, stops, refusals, outages."""

from __future__ import annotations

import asyncio
import contextlib
import gc
import itertools
import json
import signal
import time
from pathlib import Path

import pytest
from fleet_support import FleetDaemon, fleet_daemons, watcher
from inprocess_daemon import until

from robotd.fleet import topics
from robotd.fleet.broker import Broker
from robotd.fleet.orders import Action


async def read_pose_socket(path: str, poses: list[dict[str, object]]) -> None:
    """Keep every pose message of a daemon's pose socket."""
    reader, writer = await asyncio.open_unix_connection(path)
    try:
        while line := await reader.readline():
            message = json.loads(line)
            if message["type"] == "pose":
                poses.append(message)
    finally:
        writer.close()


async def test_two_daemons_publish_poses_matching_their_pose_sockets(
    tmp_path: Path, broker: Broker, fleet_key: tuple[Path, bytes]
) -> None:
    robots = [FleetDaemon(tmp_path / name, broker, name, fleet_key[0]) for name in ("r1", "r2")]
    socket_poses: dict[str, list[dict[str, object]]] = {"r1": [], "r2": []}
    async with watcher(broker) as watching, fleet_daemons(robots):
        await until(lambda: all(r.fleet.connected for r in robots), "both robots connected")
        readers = [
            asyncio.create_task(read_pose_socket(r.daemon.config.pose_socket.path, socket_poses[r.robot_id]))
            for r in robots
        ]
        await until(lambda: all(len(watching.on(topics.pose(r.robot_id))) >= 5 for r in robots), "poses of both")
        await until(lambda: all(len(poses) >= 20 for poses in socket_poses.values()), "the pose sockets")
        for robot in robots:
            status = watching.on(topics.status(robot.robot_id))[-1]
            assert status["state"] == "online"
            assert status["robot_id"] == robot.robot_id
            assert status["stop"] == {"held": False, "stops": []}
        for reader in readers:
            reader.cancel()
    for robot in robots:
        mqtt_poses = watching.on(topics.pose(robot.robot_id))
        by_t = {pose["t"]: pose for pose in socket_poses[robot.robot_id]}
        matched = [pose for pose in mqtt_poses if pose["t"] in by_t]
        assert len(matched) >= 3, f"{robot.robot_id}: MQTT poses not seen on the pose socket"
        for pose in matched:
            assert pose == by_t[pose["t"]]  # the same message, field for field
    assert {r.fleet.robot_id for r in robots} == {"r1", "r2"}


async def test_a_fleet_stop_holds_every_robot_until_released(
    tmp_path: Path, broker: Broker, fleet_key: tuple[Path, bytes]
) -> None:
    key_path, key = fleet_key
    robots = [FleetDaemon(tmp_path / name, broker, name, key_path) for name in ("r1", "r2")]
    async with watcher(broker) as watching, fleet_daemons(robots):
        await until(lambda: all(r.fleet.connected for r in robots), "both robots connected")
        for robot in robots:
            robot.command(0.3)
        await until(lambda: all(any(robot.motors.duties) for robot in robots), "both robots driving")
        published = time.monotonic()
        await watching.publish_order(key, Action.STOP, topics.FLEET)
        await until(lambda: all(not any(r.motors.duties) for r in robots), "every motor at zero")
        print(f"fleet stop: motors at zero {time.monotonic() - published:.3f} s after the publish (in-process)")
        for _ in range(10):  # commands keep coming: the stop holds
            for robot in robots:
                robot.command(0.3)
            await asyncio.sleep(0.02)
        assert all(not any(r.motors.duties) for r in robots)
        assert all(r.status()["drivers"]["fleet"]["stop"]["held"] for r in robots)
        await until(
            lambda: all(s["stop"]["held"] for s in [watching.on(topics.status(r.robot_id))[-1] for r in robots]),
            "the retained statuses to show the stop",
        )
        await watching.publish_order(key, Action.RELEASE, topics.FLEET)
        await until(lambda: all(not r.fleet.held for r in robots), "the release")
        assert all(not any(r.motors.duties) for r in robots)  # released: still at rest until a fresh command
        for robot in robots:
            robot.command(0.3)
        await until(lambda: all(any(robot.motors.duties) for robot in robots), "driving again after a fresh command")


async def test_a_robot_stop_holds_that_robot_only(
    tmp_path: Path, broker: Broker, fleet_key: tuple[Path, bytes]
) -> None:
    key_path, key = fleet_key
    robots = [FleetDaemon(tmp_path / name, broker, name, key_path) for name in ("r1", "r2")]
    async with watcher(broker) as watching, fleet_daemons(robots):
        await until(lambda: all(r.fleet.connected for r in robots), "both robots connected")
        await watching.publish_order(key, Action.STOP, "r1")
        await until(lambda: robots[0].fleet.held, "r1 held")
        await asyncio.sleep(0.2)
        assert not robots[1].fleet.held
        assert robots[1].fleet.check.counters()["accepted"] == 0


async def test_forged_and_replayed_orders_are_refused_and_counted(
    tmp_path: Path, broker: Broker, fleet_key: tuple[Path, bytes]
) -> None:
    key_path, key = fleet_key
    robot = FleetDaemon(tmp_path / "r1", broker, "r1", key_path)
    async with watcher(broker) as watching, fleet_daemons([robot]):
        await until(lambda: robot.fleet.connected, "connected")
        forged = await watching.publish_order(b"not-the-fleet-key-but-long-enough", Action.STOP, topics.FLEET)
        await until(lambda: robot.fleet.check.counters()["bad_tag"] == 1, "the forged stop refused")
        assert not robot.fleet.held
        stop = await watching.publish_order(key, Action.STOP, topics.FLEET)
        await until(lambda: robot.fleet.held, "the genuine stop")
        release = await watching.publish_order(key, Action.RELEASE, topics.FLEET)
        await until(lambda: not robot.fleet.held, "the genuine release")
        await watching.client.publish(topics.FLEET_STOP, stop, qos=1, retain=True)  # the old stop, replayed
        await until(lambda: robot.fleet.check.counters()["replayed"] == 1, "the replayed stop refused")
        await watching.publish_order(key, Action.STOP, topics.FLEET)
        await until(lambda: robot.fleet.held, "a new stop")
        await watching.client.publish(topics.FLEET_STOP, release, qos=1, retain=True)  # the old release, replayed
        await until(lambda: robot.fleet.check.counters()["replayed"] == 2, "the replayed release refused")
        assert robot.status()["drivers"]["fleet"]["stop"]["held"]  # the replayed release released nothing
        await watching.client.publish(topics.FLEET_STOP, b"", qos=1, retain=True)  # the retained stop deleted
        await until(lambda: robot.fleet.check.counters()["cleared"] == 1, "the deletion seen")
        assert robot.status()["drivers"]["fleet"]["stop"]["held"]
        counts = robot.status()["drivers"]["fleet"]["orders"]
        assert counts["bad_tag"] == 1
        assert counts["replayed"] == 2
        assert counts["accepted"] == 3
    assert forged != stop


async def test_the_link_reconnects_after_the_broker_was_away_and_the_control_loop_keeps_time(
    tmp_path: Path, broker: Broker, fleet_key: tuple[Path, bytes]
) -> None:
    robot = FleetDaemon(tmp_path / "r1", broker, "r1", fleet_key[0], reconnect_max_s=0.2, pose_rate_hz=50.0)
    ticks: list[float] = []
    periods = robot.daemon.control_periods
    original_tick = periods.tick

    def recorded_tick(now: float) -> None:
        ticks.append(now)
        original_tick(now)

    periods.tick = recorded_tick  # type: ignore[method-assign]

    async def operator() -> None:
        """Teleop held throughout, so the control loop steps every period (at rest it hardly wakes)."""
        while True:
            robot.command(0.05)
            await asyncio.sleep(0.1)

    async with fleet_daemons([robot]):
        await until(lambda: robot.fleet.connected, "connected")
        driving = asyncio.create_task(operator())
        await asyncio.sleep(0.2)
        outage_from = len(ticks)
        await asyncio.to_thread(broker.stop)
        await until(lambda: not robot.fleet.connected, "the loss seen")
        await asyncio.sleep(1.0)  # the outage (robotd bench fleet measures a 30 s one)
        await until(lambda: robot.fleet.counts["dropped"] > 0, "poses dropped while the broker is away")
        await asyncio.to_thread(broker.start)
        await until(lambda: robot.fleet.connected and robot.fleet.counts["connects"] == 2, "reconnected", 20.0)
        outage = ticks[outage_from:]
        driving.cancel()
    assert robot.fleet.counts["connection_losses"] == 1
    assert len(outage) > 30  # the control loop ran throughout (50 Hz over well over a second)
    worst = max(b - a for a, b in itertools.pairwise(outage))
    print(f"broker outage: {len(outage)} control ticks, worst interval {worst * 1e3:.1f} ms (period 20 ms)")
    assert worst < 1.0  # a generous functional bound: the loop never waited for the broker


@pytest.mark.parametrize("cap_s", [0.4, 1.0])
async def test_reconnection_backs_off_to_its_cap(tmp_path: Path, fleet_key: tuple[Path, bytes], cap_s: float) -> None:
    """No broker at all, a fake sleep: each failed attempt waits twice as long as the previous one, up to the cap."""
    from inprocess_daemon import daemon_config  # noqa: PLC0415

    from robotd.fleet.broker import free_tcp_port  # noqa: PLC0415
    from robotd.fleet.link import FleetLink  # noqa: PLC0415

    config = daemon_config(
        tmp_path,
        fleet={"enabled": True, "robot_id": "r1", "port": free_tcp_port(), "key_file": str(fleet_key[0]),
               "reconnect_max_s": cap_s},
    ).fleet  # fmt: skip
    delays: list[float] = []

    async def fake_sleep(delay: float) -> None:
        delays.append(delay)
        if len(delays) >= 6:
            raise asyncio.CancelledError
        await asyncio.sleep(0)

    link = FleetLink(config, status_source=dict, on_hold=lambda _held: None, sleep=fake_sleep)
    with pytest.raises(asyncio.CancelledError):
        await link._connection()
    assert delays == [min(0.1 * 2**n, cap_s) for n in range(6)]
    assert link.counts["connects"] == 0


async def test_a_hung_broker_does_not_delay_the_daemons_exit(
    tmp_path: Path, broker: Broker, fleet_key: tuple[Path, bytes]
) -> None:
    """The broker stopped (SIGSTOP) while connected: the daemon still ends at once, motors zeroed."""
    robot = FleetDaemon(tmp_path / "r1", broker, "r1", fleet_key[0])
    task = asyncio.create_task(robot.daemon.run())
    try:
        await until(lambda: robot.fleet.connected, "connected")
        assert broker.proc is not None
        broker.proc.send_signal(signal.SIGSTOP)
        robot.command(0.3)
        await until(lambda: any(robot.motors.duties), "driving")
        started = time.monotonic()
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        ended = time.monotonic() - started
    finally:
        if broker.proc is not None:
            broker.proc.send_signal(signal.SIGCONT)
        gc.unfreeze()
    print(f"daemon exit with a hung broker: {ended * 1e3:.0f} ms")
    assert not any(robot.motors.duties)
    assert ended < 2.0  # well below the client's 5 s timeout: the exit never waits for the broker
