"""The operator's side of the fleet: watch every robot, publish signed stops and releases (`robotd fleet`)."""

from __future__ import annotations

import asyncio
import contextlib
import getpass
import socket
import ssl
import sys
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlsplit

import aiomqtt

from robotd.fleet import topics
from robotd.fleet.orders import Action, sign
from robotd.fleet.secrets import Credentials
from robotd.fleet.viewer import FleetView

RETAINED_WAIT_S = 0.5  # the broker sends retained messages right after the subscription: this is plenty on a LAN
CLEAR_SCREEN = "\x1b[H\x1b[2J"


@dataclass(frozen=True, slots=True)
class BrokerAddress:
    """Where the broker is and how to reach it: mqtt://HOST:PORT, or mqtts:// for TLS."""

    host: str
    port: int
    tls: bool

    @classmethod
    def parse(cls, url: str) -> BrokerAddress:
        """From mqtt://HOST[:PORT] or mqtts://HOST[:PORT] (ValueError otherwise)."""
        parts = urlsplit(url)
        if parts.scheme not in ("mqtt", "mqtts") or not parts.hostname:
            raise ValueError(f"a broker is mqtt://HOST:PORT or mqtts://HOST:PORT, got {url!r}")
        tls = parts.scheme == "mqtts"
        return cls(parts.hostname, parts.port or (8883 if tls else 1883), tls)

    def __str__(self) -> str:
        return f"{'mqtts' if self.tls else 'mqtt'}://{self.host}:{self.port}"


@contextlib.asynccontextmanager
async def connect(
    address: BrokerAddress, credentials: Credentials | None, ca_file: str | None = None
) -> AsyncIterator[aiomqtt.Client]:
    """An operator's connection (a random client id: several viewers may watch at once)."""
    context = ssl.create_default_context(cafile=ca_file) if address.tls else None
    async with aiomqtt.Client(
        address.host,
        address.port,
        username=credentials.username if credentials else None,
        password=credentials.password if credentials else None,
        tls_context=context,
        timeout=5.0,
    ) as client:
        yield client


def issuer() -> str:
    """Who signs: user@host, shown in every robot's status and log."""
    return f"{getpass.getuser()}@{socket.gethostname()}"[:128]


async def retained_stops(client: aiomqtt.Client) -> dict[str, str]:
    """The action of the retained order on every stop topic (target -> stop/release), as the broker holds them now."""
    view = FleetView()
    await client.subscribe(topics.ALL_STOPS, qos=1)
    with contextlib.suppress(TimeoutError):
        async with asyncio.timeout(RETAINED_WAIT_S):
            async for message in client.messages:
                payload = message.payload if isinstance(message.payload, bytes) else b""
                view.take(message.topic.value, payload, time.monotonic())
    return view.stops


async def send_orders(
    address: BrokerAddress,
    credentials: Credentials | None,
    key: bytes,
    action: Action,
    *,
    target: str | None,
    ca_file: str | None = None,
) -> list[str]:
    """Publish a retained signed order; with no target, to the fleet (a release also to every robot held on its own).

    Returns the topics published to.
    """
    async with connect(address, credentials, ca_file) as client:
        if target is not None:
            targets = [target]
        elif action is Action.STOP:
            targets = [topics.FLEET]
        else:
            held = await retained_stops(client)
            targets = [topics.FLEET, *sorted(t for t, a in held.items() if a == "stop" and t != topics.FLEET)]
        for name in targets:
            # each order later than the one before, even within one clock tick
            payload = sign(key, action, name, time.time_ns(), issuer())
            await client.publish(topics.stop(name), payload, qos=1, retain=True)
        return [topics.stop(name) for name in targets]


async def watch(
    address: BrokerAddress,
    credentials: Credentials | None,
    *,
    duration_s: float | None,
    refresh_s: float = 0.5,
    in_place: bool = True,
    write: Callable[[str], object] | None = None,
    ca_file: str | None = None,
) -> FleetView:
    """Show the table every `refresh_s` (redrawn in place on a terminal) for `duration_s` or until cancelled."""
    view = FleetView()
    if write is None:  # the stdout of now, not of when this module was imported (a test's capture, a redirection)
        write = sys.stdout.write
    async with connect(address, credentials, ca_file) as client:
        await client.subscribe([(topics.ALL_POSES, 0), (topics.ALL_STATUSES, 1), (topics.ALL_STOPS, 1)])

        async def collect() -> None:
            async for message in client.messages:
                payload = message.payload if isinstance(message.payload, bytes) else b""
                view.take(message.topic.value, payload, time.monotonic())

        collector = asyncio.create_task(collect())
        started = time.monotonic()
        try:
            while duration_s is None or time.monotonic() - started < duration_s:
                await asyncio.sleep(refresh_s if duration_s is None else min(refresh_s, duration_s))
                table = view.render(time.monotonic(), str(address))
                write((CLEAR_SCREEN if in_place else "") + table + "\n")
                if hasattr(sys.stdout, "flush"):
                    sys.stdout.flush()
        finally:
            collector.cancel()
            with contextlib.suppress(asyncio.CancelledError, aiomqtt.MqttError):
                await collector
    return view


def read_key(path: Path) -> bytes:
    """The fleet key for signing (the same checks as the daemon's)."""
    from robotd.fleet.secrets import load_fleet_key  # noqa: PLC0415

    return load_fleet_key(path, "--key")
