"""`robotd fleet view`: the whole fleet in Foxglove, from the broker (robotd.fleet.fleet_scene draws it).

Theory of operation. One Foxglove WebSocket server (foxglove-sdk, on a private context) runs for the life of the
command; an MQTT client subscribes to every robot's pose and status as `robotd fleet` does (same broker address,
credentials, TLS) and hands each message to a `FleetScene`, which publishes it on the robot's channels. The first
connection must succeed (a wrong broker or password is a one-line error); a connection lost later is said once and
retried with robotd's backoff while the server keeps serving what it has. The broker sends every retained status on
each subscription, so robots that left (their last will `offline`) show as offline, and robots that appear later
get their channels when their first message arrives.
"""

from __future__ import annotations

import asyncio
import sys
from collections.abc import Callable
from dataclasses import dataclass

import aiomqtt
import foxglove

from drivers.backoff import Backoff
from robotd.fleet import topics
from robotd.fleet.fleet_scene import FleetScene
from robotd.fleet.operator import BrokerAddress, connect
from robotd.fleet.secrets import Credentials

FIRST_RETRY_S = 0.5
RETRY_CAP_S = 10.0
CLIENT_BACKLOG = 1024  # messages buffered per viewer: a slow viewer loses the oldest


@dataclass(frozen=True, slots=True)
class ViewServer:
    """Where the view listens (port 0 picks a free one) and how long its trails reach."""

    host: str = "127.0.0.1"
    port: int = 8765
    trail_s: float = 120.0


async def serve_fleet_view(
    address: BrokerAddress,
    credentials: Credentials | None,
    server: ViewServer,
    *,
    duration_s: float | None = None,
    ca_file: str | None = None,
    on_ready: Callable[[int], object] | None = None,
) -> FleetScene:
    """Serve the fleet until cancelled (or for `duration_s`); `on_ready(port)` once the server and the first broker
    connection are up. Raises RuntimeError when the port cannot be served, aiomqtt.MqttError when the broker
    cannot be reached at first."""
    context = foxglove.Context()
    fleet = FleetScene(context, trail_s=server.trail_s)
    websocket = foxglove.start_server(
        name="robotd fleet", host=server.host, port=server.port, context=context, message_backlog_size=CLIENT_BACKLOG
    )
    try:
        async with asyncio.timeout(duration_s):
            await _follow(address, credentials, ca_file, fleet, lambda: on_ready and on_ready(websocket.port))
    except TimeoutError:
        pass
    finally:
        websocket.stop()
    return fleet


async def _follow(
    address: BrokerAddress,
    credentials: Credentials | None,
    ca_file: str | None,
    fleet: FleetScene,
    ready: Callable[[], object],
) -> None:
    backoff = Backoff(FIRST_RETRY_S, RETRY_CAP_S)
    first = True
    while True:
        try:
            async with connect(address, credentials, ca_file) as client:
                await client.subscribe([(topics.ALL_POSES, 0), (topics.ALL_STATUSES, 1)])
                backoff.reset()
                if first:
                    first = False
                    ready()
                else:
                    print(f"robotd fleet view: broker {address}: connected again", file=sys.stderr, flush=True)
                async for message in client.messages:
                    payload = message.payload if isinstance(message.payload, bytes) else b""
                    fleet.take(message.topic.value, payload)
        except aiomqtt.MqttError as error:
            if first:
                raise
            delay = backoff.next_delay()
            print(
                f"robotd fleet view: broker {address}: {error}; retrying in {delay:.1f} s (the view keeps serving)",
                file=sys.stderr,
                flush=True,
            )
            await asyncio.sleep(delay)
