"""`robotd fleet` against a real broker and an in-process daemon: the table, stop and release; the broker's ACLs."""

from __future__ import annotations

import asyncio
from pathlib import Path

import aiomqtt
import pytest
from fleet_support import FleetDaemon, fleet_daemons, watcher
from inprocess_daemon import until

from robotd.cli import main
from robotd.fleet import topics
from robotd.fleet.broker import OPERATOR, Broker, robot_user
from robotd.fleet.orders import Action, sign


def cli_args(broker: Broker, *args: str) -> list[str]:
    setup = broker.setup
    return ["fleet", *args, "--broker", setup.url, "--credentials", str(setup.credentials_file(OPERATOR))]


async def test_stop_all_then_release_all_from_the_command_line(
    tmp_path: Path, broker: Broker, fleet_key: tuple[Path, bytes], capsys: pytest.CaptureFixture[str]
) -> None:
    robots = [FleetDaemon(tmp_path / name, broker, name, fleet_key[0]) for name in ("r1", "r2")]
    async with fleet_daemons(robots):
        await until(lambda: all(r.fleet.connected for r in robots), "both robots connected")
        assert await asyncio.to_thread(main, cli_args(broker, "stop", "--all", "--key", str(fleet_key[0]))) == 0
        await until(lambda: all(r.fleet.held for r in robots), "every robot held")
        assert await asyncio.to_thread(main, cli_args(broker, "stop", "r2", "--key", str(fleet_key[0]))) == 0
        await until(lambda: len(robots[1].fleet.hold.describe()["stops"]) == 2, "r2's own stop as well")
        capsys.readouterr()
        assert await asyncio.to_thread(main, ["fleet", "--once", "--broker", broker.setup.url, "--credentials",
                                              str(broker.setup.credentials_file(OPERATOR))]) == 0  # fmt: skip
        table = capsys.readouterr().out
        assert "2 robot(s)" in table
        assert "FLEET STOP retained" in table
        rows = [line.split() for line in table.splitlines() if line.split()[:1] in (["r1"], ["r2"])]
        assert [row[0] for row in rows] == ["r1", "r2"]
        assert all(row[1] == "online" and "HELD" in row for row in rows)
        assert await asyncio.to_thread(main, cli_args(broker, "release", "--all", "--key", str(fleet_key[0]))) == 0
        await until(lambda: not any(r.fleet.held for r in robots), "every robot released, r2's own stop too")
        assert "robotd/r2/stop" in capsys.readouterr().out


def test_an_order_needs_the_key(broker: Broker, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(cli_args(broker, "stop", "--all")) == 2
    assert "--key" in capsys.readouterr().err


async def test_a_robot_cannot_write_the_stop_topics(broker: Broker, fleet_key: tuple[Path, bytes]) -> None:
    """The generated ACL: a robot's user publishing a (validly signed) release is dropped by the broker."""
    setup = broker.setup
    user = robot_user("r1")
    async with watcher(broker) as watching:
        async with aiomqtt.Client("127.0.0.1", setup.port, username=user, password=setup.passwords[user]) as robot:
            release = sign(fleet_key[1], Action.RELEASE, topics.FLEET, 1, "r1")
            await robot.publish(topics.FLEET_STOP, release, qos=1, retain=True)
            await robot.publish(topics.pose("r2"), b"{}", qos=1)  # another robot's pose
            await robot.publish(topics.pose("r1"), b'{"x": 1}', qos=1)  # its own: allowed
        await until(lambda: bool(watching.on(topics.pose("r1"))), "r1's own pose")
        await asyncio.sleep(0.2)
        assert watching.on(topics.FLEET_STOP) == []
        assert watching.on(topics.pose("r2")) == []
