"""The daemon's fleet link: pose and status to an MQTT broker, fleet stops from it, never in the control loop's way.

Theory of operation. The daemon hands the link its latest pose message (an attribute write) and reads `held`; it
never awaits the link. The link's own tasks sample the pose at `fleet.pose_rate_hz` and the status every
`fleet.status_period_s` (and at once when the stop changes) into a bounded outbox: when the broker is slow or away
the oldest messages are dropped and counted (`dropped`), so memory stays bounded and nothing waits. One sender hands
the outbox to the MQTT client only while its socket has nothing left unsent (paho's `want_write`), so a broker that
stops reading backs the messages up in the outbox, not in paho's unbounded buffer.

Connection. aiomqtt connects (in an executor thread: no blocking on the loop) with the credentials, TLS and a last
will, the retained status `{"state": "offline"}`, which the broker publishes when the robot vanishes without a
clean disconnect (SIGKILL, power, network) within 1.5 keep-alives. The link subscribes to its two stop topics at QoS
1 and publishes its retained status `{"state": "online", ...}`; a clean exit publishes `offline` itself. A lost
connection is logged once and retried with `drivers.backoff.Backoff` up to `fleet.reconnect_max_s`; every retained
order is delivered again on resubscription (a repeat, not a replay: see robotd.fleet.orders).

Stops. An accepted order changes the `StopHold`; when the robot goes from free to held (or back) `on_hold(held)` is
called at once on the loop, and the daemon cuts the motors in the same call. A robot that loses the broker keeps its
hold as it was and keeps obeying its local deadman; it cannot be released until the broker is back.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import time
from collections import deque
from collections.abc import Awaitable, Callable
from typing import Any

import aiomqtt

from drivers.backoff import Backoff
from robotd.config.fleet import FleetConfig
from robotd.daemon import posesock
from robotd.fleet import topics
from robotd.fleet.orders import OrderCheck, StopHold
from robotd.fleet.secrets import Credentials, load_credentials, load_fleet_key, tls_context

log = logging.getLogger("robotd.fleet")

FIRST_RETRY_S = 0.1
BACKED_UP_POLL_S = 0.01  # while paho still has bytes to write, look again this often
EXIT_WAIT_S = 0.1  # on the daemon's way out, the longest wait for the broker: the motors are zeroed after the tasks end
REFUSAL_LOG_PERIOD_S = 10.0

StatusSource = Callable[[], dict[str, Any]]
Outgoing = tuple[str, bytes, int, bool]  # topic, payload, QoS, retain


def offline_payload(robot_id: str) -> bytes:
    """The retained status of a robot that is gone (its last will, or its clean exit)."""
    return json.dumps({"state": "offline", "robot_id": robot_id}).encode()


def fleet_status(robot_id: str, status: dict[str, Any], stop: dict[str, Any]) -> dict[str, Any]:
    """The retained status a fleet viewer needs, from the daemon's status message (see the daemon's `_fleet_status`)."""
    drivers = status.get("drivers", {})
    control = drivers.get("control", {})
    return {
        "state": "online",
        "robot_id": robot_id,
        "stamp": status.get("stamp"),
        "odometry": drivers.get("encoders", {}).get("state"),
        "fix": drivers.get("marvelmind", {}).get("state"),
        "control": control.get("state"),
        "faults": control.get("faults", []),
        "calibration": status.get("calibration", {}),
        "stop": stop,
    }


class _LeavingError(Exception):
    """The link's run() was cancelled: the session ends (see FleetLink._stopping)."""


class FleetLink:
    """The robot's MQTT client (see the module docstring); `run()` is one task of the daemon's TaskGroup."""

    def __init__(
        self,
        config: FleetConfig,
        *,
        status_source: StatusSource,
        on_hold: Callable[[bool], None],
        wall_clock: Callable[[], float] = time.time,
        sleep: Callable[[float], Awaitable[None]] = asyncio.sleep,
    ) -> None:
        self.config = config
        self.robot_id = config.robot_id
        self.check = OrderCheck(load_fleet_key(config.key_file), config.robot_id, config.max_clock_offset_s)
        self.credentials: Credentials | None = (
            load_credentials(config.credentials_file) if config.credentials_file else None
        )
        self.tls = tls_context(config)
        self.hold = StopHold()
        self.latest_pose: dict[str, Any] | None = None  # written by the daemon at every pose it publishes
        self.connected = False
        self._status_source = status_source
        self._on_hold = on_hold
        self._wall_clock = wall_clock
        self._sleep = sleep
        self._outbox: deque[Outgoing] = deque()
        self._outbox_ready = asyncio.Event()
        self._status_due = asyncio.Event()
        self._last_refusal_log = -float("inf")
        self._leaving = False  # cancelled: the daemon is stopping
        self._leave = asyncio.Event()  # set when run() is cancelled, whatever aiomqtt did with its own tasks' cancels
        self.counts: dict[str, int] = dict.fromkeys(
            ("connects", "connection_losses", "published", "dropped", "poses", "statuses"), 0
        )

    @property
    def held(self) -> bool:
        """Whether a fleet stop holds the robot."""
        return self.hold.held

    @property
    def broker(self) -> str:
        """The broker's address, for messages."""
        scheme = "mqtts" if self.config.tls else "mqtt"
        return f"{scheme}://{self.config.host}:{self.config.port}"

    def counters(self) -> dict[str, Any]:
        """The link's state for the daemon's status message."""
        return {
            "connected": self.connected,
            "queued": len(self._outbox),
            **self.counts,
            "stop": self.hold.describe(),
            "orders": self.check.counters(),
        }

    def offer(self, topic: str, payload: bytes, qos: int = 0, retain: bool = False) -> None:
        """Queue a message for the broker without waiting; past fleet.queue_size the oldest is dropped and counted."""
        if len(self._outbox) >= self.config.queue_size:
            self._outbox.popleft()
            self.counts["dropped"] += 1
        self._outbox.append((topic, payload, qos, retain))
        self._outbox_ready.set()

    # --- tasks ----------------------------------------------------------------------------------------------

    async def run(self) -> None:
        """Sample pose and status, and keep a connection to the broker, until cancelled."""
        async with asyncio.TaskGroup() as tasks:
            tasks.create_task(self._pose_sampler(), name="fleet-pose")
            tasks.create_task(self._status_sampler(), name="fleet-status")
            tasks.create_task(self._connection(), name="fleet-connection")
            tasks.create_task(self._stopping(), name="fleet-stopping")

    async def _stopping(self) -> None:
        """Wait for run()'s cancellation, and make it reach the connection whatever aiomqtt did with it.

        aiomqtt waits with asyncio.wait_for, which on Python 3.11 drops a cancellation that arrives as the wait ends
        (a subscribe or publish answered at the moment the daemon stops): the connection's task would then carry on
        and the daemon's exit would wait for it forever. This task's plain wait always receives its cancellation.
        """
        try:
            await asyncio.Event().wait()
        finally:
            self._leaving = True
            self._leave.set()
            self._outbox_ready.set()  # a sender waiting for work sees the leave at once

    async def _until_leaving(self) -> None:
        await self._leave.wait()
        raise _LeavingError  # an error, not CancelledError: a TaskGroup ignores a child that ends cancelled

    async def _pose_sampler(self) -> None:
        period = 1.0 / self.config.pose_rate_hz
        sent: dict[str, Any] | None = None
        while True:
            await asyncio.sleep(period)
            pose = self.latest_pose
            if pose is not None and pose is not sent:  # a new pose since the last one sent (not a repeat)
                sent = pose
                self.counts["poses"] += 1
                self.offer(topics.pose(self.robot_id), posesock.encode(pose).rstrip(b"\n"))

    async def _status_sampler(self) -> None:
        while True:
            with contextlib.suppress(TimeoutError):  # asyncio.timeout: 3.11's wait_for can drop a cancellation
                async with asyncio.timeout(self.config.status_period_s):
                    await self._status_due.wait()
            self._status_due.clear()
            self._offer_status()

    def _offer_status(self) -> None:
        status = fleet_status(self.robot_id, self._status_source(), self.hold.describe())
        self.counts["statuses"] += 1
        self.offer(topics.status(self.robot_id), posesock.encode(status).rstrip(b"\n"), qos=1, retain=True)

    async def _connection(self) -> None:
        backoff = Backoff(FIRST_RETRY_S, self.config.reconnect_max_s)
        lost_logged = False
        while not self._leave.is_set():
            try:
                async with self._client() as client:
                    self.connected = True
                    self.counts["connects"] += 1
                    backoff.reset()
                    log.info("fleet: connected to %s as %s", self.broker, self.robot_id)
                    lost_logged = False
                    await self._session(client)
            except* (aiomqtt.MqttError, OSError) as group:
                if self._leaving:  # the disconnection's error on the way out must not swallow the cancellation
                    raise asyncio.CancelledError from None
                error = group.exceptions[0]
                if self.connected:
                    self.counts["connection_losses"] += 1
                if not lost_logged:
                    lost_logged = True
                    log.warning("fleet: broker %s unavailable (%s): reconnecting with backoff", self.broker, error)
                else:
                    log.debug("fleet: broker %s still unavailable: %s", self.broker, error)
            finally:
                self.connected = False
            await self._sleep(backoff.next_delay())

    def _client(self) -> aiomqtt.Client:
        credentials = self.credentials
        return aiomqtt.Client(
            self.config.host,
            self.config.port,
            username=credentials.username if credentials else None,
            password=credentials.password if credentials else None,
            identifier=f"robotd-{self.robot_id}",
            will=aiomqtt.Will(topics.status(self.robot_id), offline_payload(self.robot_id), qos=1, retain=True),
            keepalive=self.config.keepalive_s,
            timeout=max(2.0, float(self.config.keepalive_s)),
            tls_context=self.tls,
            clean_session=True,
        )

    async def _session(self, client: aiomqtt.Client) -> None:
        try:
            await client.subscribe([(topic, 1) for topic in self.check.topics()])
            self._status_due.set()  # `online` at once, before the poses waiting in the outbox
            async with asyncio.TaskGroup() as tasks:
                tasks.create_task(self._receive(client), name="fleet-receive")
                tasks.create_task(self._send(client), name="fleet-send")
                tasks.create_task(self._until_leaving(), name="fleet-leaving")
        except ExceptionGroup as group:
            if group.subgroup(_LeavingError) is None:
                raise  # the connection failed: _connection reconnects
            self._say_offline(client)
            raise asyncio.CancelledError from None
        except asyncio.CancelledError:
            self._say_offline(client)
            raise

    def _say_offline(self, client: aiomqtt.Client) -> None:
        """The daemon is stopping and zeroes the motors only once every task has ended: say `offline` without
        waiting (paho writes it now if the socket takes it), and bound the disconnection's wait."""
        self._leaving = True
        client.timeout = EXIT_WAIT_S
        with contextlib.suppress(Exception):
            client._client.publish(topics.status(self.robot_id), offline_payload(self.robot_id), 1, True)

    async def _send(self, client: aiomqtt.Client) -> None:
        paho = client._client  # (private: aiomqtt exposes no other way to see paho's unsent bytes)
        # `_leave` checked as well as cancellation: aiomqtt's publish can swallow a cancellation (see _stopping)
        while not self._leave.is_set():
            await self._outbox_ready.wait()
            while self._outbox and not self._leave.is_set():
                if paho.want_write():  # the broker is not keeping up: let the outbox take the backlog
                    await asyncio.sleep(BACKED_UP_POLL_S)
                    continue
                topic, payload, qos, retain = self._outbox.popleft()
                await client.publish(topic, payload, qos, retain)
                self.counts["published"] += 1
            self._outbox_ready.clear()

    async def _receive(self, client: aiomqtt.Client) -> None:
        async for message in client.messages:
            payload = message.payload
            data = payload if isinstance(payload, bytes) else str(payload or "").encode()
            self.on_order(message.topic.value, data)

    def on_order(self, topic: str, payload: bytes) -> None:
        """One message on a stop topic: a genuine new order changes the hold (and the motors, through on_hold)."""
        before = self.check.counters()
        order = self.check.check(topic, payload, self._wall_clock())
        if order is None:
            after = self.check.counters()
            refused = [name for name, count in after.items() if count > before[name] and name != "repeats"]
            if refused:
                self._log_refusal(topic, refused[0])
            return
        changed = self.hold.apply(order)
        log.warning(
            "fleet: %s from %s for %s accepted: robot %s",
            order.action.value, order.issuer or "?", order.target, "held stopped" if self.held else "released",
        )  # fmt: skip
        if changed:
            self._on_hold(self.held)
        self._status_due.set()

    def _log_refusal(self, topic: str, reason: str) -> None:
        now = time.monotonic()
        if now - self._last_refusal_log >= REFUSAL_LOG_PERIOD_S:
            self._last_refusal_log = now
            log.warning("fleet: order on %s refused (%s); counted in the status", topic, reason)
