"""In-process fleet tests: daemons with fake wheels on a real broker, an MQTT watcher, signed orders.

The daemons are the real `Daemon` with the stand-ins of inprocess_daemon (FakeEncoders, FakeMotors: see what they do
not model there) on the real clock; the broker is a real mosquitto (tests/support/mosquitto.py).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiomqtt
from inprocess_daemon import FakeEncoders, FakeMotors, daemon_config, running
from mosquitto import fleet_section

from robotd.daemon.service import Daemon
from robotd.fleet import topics
from robotd.fleet.broker import OPERATOR, Broker
from robotd.fleet.orders import Action, sign


class FleetDaemon:
    """A daemon with fake wheels and the fleet link on, and the motors it drove."""

    def __init__(self, folder: Path, broker: Broker, robot_id: str, key_file: Path, **fleet: object) -> None:
        folder.mkdir(parents=True, exist_ok=True)
        config = daemon_config(
            folder,
            fleet=fleet_section(broker, robot_id, key_file, **fleet),
            control={"stall_timeout_s": 5.0},  # no physics turns the fake wheels: the stall guard must wait
        )
        self.motor_outputs: list[FakeMotors] = []
        self.daemon = Daemon(config, encoders=FakeEncoders(time.monotonic), motors_factory=self._motors)
        assert self.daemon.fleet is not None
        self.fleet = self.daemon.fleet
        self.robot_id = robot_id
        self._sequence = 0

    def _motors(self) -> FakeMotors:
        motors = FakeMotors()
        self.motor_outputs.append(motors)
        return motors

    @property
    def motors(self) -> FakeMotors:
        """The motor outputs connected last."""
        return self.motor_outputs[-1]

    def command(self, vx: float) -> None:
        """A valid teleop command arriving now."""
        from robotd.daemon.teleop import TeleopCommand  # noqa: PLC0415
        from robotd.kinematics import Twist  # noqa: PLC0415

        self._sequence += 1
        self.daemon._on_teleop(TeleopCommand(Twist(vx, 0.0, 0.0), 1, self._sequence, time.monotonic()))

    def status(self) -> dict[str, Any]:
        """The daemon's status message now."""
        return self.daemon._status_message(time.monotonic())


@contextlib.asynccontextmanager
async def fleet_daemons(daemons: list[FleetDaemon]) -> AsyncIterator[None]:
    """Every daemon's `run()` on this loop until the block ends."""
    async with contextlib.AsyncExitStack() as stack:
        for fleet_daemon in daemons:
            await stack.enter_async_context(running(fleet_daemon.daemon))
        yield


class Watcher:
    """An operator's MQTT client that keeps every message of the robotd tree, with its arrival time."""

    def __init__(self, client: aiomqtt.Client) -> None:
        self.client = client
        self.messages: list[tuple[float, str, bytes, bool]] = []

    async def collect(self) -> None:
        """Keep messages until cancelled."""
        async for message in self.client.messages:
            payload = message.payload if isinstance(message.payload, bytes) else b""
            self.messages.append((time.monotonic(), message.topic.value, payload, message.retain))

    def on(self, topic: str) -> list[dict[str, Any]]:
        """The JSON messages on `topic` so far."""
        return [json.loads(payload) for _t, name, payload, _r in self.messages if name == topic and payload]

    async def publish_order(self, key: bytes, action: Action, target: str, time_ns: int | None = None) -> bytes:
        """Sign and publish a retained order; returns its payload (to replay it)."""
        payload = sign(key, action, target, time_ns or time.time_ns(), "test")
        await self.client.publish(topics.stop(target), payload, qos=1, retain=True)
        return payload


def watcher(broker: Broker) -> contextlib.AbstractAsyncContextManager[Watcher]:
    """A Watcher subscribed to the whole tree as the operator."""
    return watcher_at(broker.setup.port, broker.setup.passwords[OPERATOR])


@contextlib.asynccontextmanager
async def watcher_at(port: int, password: str) -> AsyncIterator[Watcher]:
    """A Watcher subscribed to the whole tree as the operator of the broker on `port`."""
    async with aiomqtt.Client(
        "127.0.0.1", port, username=OPERATOR, password=password, identifier="test-watcher"
    ) as client:
        await client.subscribe(f"{topics.ROOT}/#", qos=1)
        watching = Watcher(client)
        task = asyncio.create_task(watching.collect())
        try:
            yield watching
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
