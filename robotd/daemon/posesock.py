"""The pose stream: newline-delimited JSON on a Unix socket, one bounded queue per client.

Theory of operation. Message builders are pure functions returning plain dicts. `PoseServer.publish` encodes a
message once and appends it to every client's queue without awaiting anything, so the producer (the control and
filter loops) is never delayed by a client. Each client has a writer task that moves its queue into the socket;
a queue is a bounded deque, so a slow client loses its oldest messages, and a client whose socket accepts nothing
for `stall_s` while messages wait is disconnected. Every client receives the `hello` message first; a client beyond
`max_clients` receives one `error` message instead, then the close.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import json
import logging
import math
import os
import socket
import stat
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

PROTOCOL = "robotd-pose"
PROTOCOL_VERSION = 1
CLOSE_TIMEOUT_S = 1.0  # a client's task still running this long after close() is cancelled


def hello_message(rate_hz: float, status_rate_hz: float) -> dict[str, Any]:
    """The first message every client receives."""
    return {
        "type": "hello",
        "protocol": PROTOCOL,
        "version": PROTOCOL_VERSION,
        "rate_hz": rate_hz,
        "status_rate_hz": status_rate_hz,
    }


def pose_message(
    *,
    t: float,
    stamp: float,
    pose: Sequence[float],
    twist: Sequence[float],
    covariance: Sequence[Sequence[float]] | Sequence[float],
    fix_age_s: float | None,
    fix_state: str,
    odometry_state: str,
) -> dict[str, Any]:
    """A pose: x, y, theta in the map frame; vx, vy, wz in the body frame; the 3x3 covariance of (x, y, theta)."""
    x, y, theta = pose
    vx, vy, wz = twist
    flat = [float(v) for row in covariance for v in (row if isinstance(row, Sequence) else (row,))]
    if len(flat) != 9:
        raise ValueError(f"covariance must be 3x3, got {len(flat)} values")
    return {
        "type": "pose",
        "t": t,
        "stamp": stamp,
        "frame_id": "map",
        "child_frame_id": "base_link",
        "x": x,
        "y": y,
        "theta": theta,
        "vx": vx,
        "vy": vy,
        "wz": wz,
        "covariance": flat,
        "fix_age_s": fix_age_s,
        "fix_state": fix_state,
        "odometry_state": odometry_state,
    }


def status_message(
    *, t: float, stamp: float, drivers: Mapping[str, Mapping[str, Any]], filter_diagnostics: Mapping[str, Any]
) -> dict[str, Any]:
    """Health: the counters of every driver by name, and the filter's diagnostics."""
    return {
        "type": "status",
        "t": t,
        "stamp": stamp,
        "drivers": {name: dict(counters) for name, counters in drivers.items()},
        "filter": dict(filter_diagnostics),
    }


def error_message(error: str) -> dict[str, Any]:
    """Why the server is about to close this client's connection."""
    return {"type": "error", "error": error}


def encode(message: Mapping[str, Any]) -> bytes:
    """One JSON line; non-finite numbers become null (JSON has no NaN)."""
    return json.dumps(_finite(message), separators=(",", ":"), allow_nan=False).encode() + b"\n"


def _finite(value: Any) -> Any:
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, Mapping):
        return {str(k): _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    return value


@dataclass(slots=True)
class _Client:
    """One connected reader."""

    queue: collections.deque[bytes]
    wake: asyncio.Event
    dropped: int = 0


class PoseServer:
    """Serves published messages to every client of a Unix socket; `publish` never blocks."""

    def __init__(
        self,
        path: str | Path,
        mode: int = 0o660,
        *,
        hello: Mapping[str, Any] | None = None,
        queue_size: int = 64,
        stall_s: float = 5.0,
        max_clients: int = 16,
    ) -> None:
        self.path = Path(path)
        self.mode = mode
        self.hello = encode(hello if hello is not None else hello_message(0.0, 0.0))
        self.queue_size = queue_size
        self.stall_s = stall_s
        self.max_clients = max_clients
        self._server: asyncio.AbstractServer | None = None
        self._clients: dict[asyncio.Task[None], _Client] = {}
        self._closing = asyncio.Event()
        self._listened = asyncio.Event()  # set while at least one client is connected
        self.counters = {"connected": 0, "refused": 0, "dropped_messages": 0, "stalled": 0, "published": 0}

    @property
    def clients(self) -> int:
        """Clients connected now."""
        return len(self._clients)

    async def wait_for_clients(self) -> None:
        """Return once at least one client is connected (at once if one is)."""
        await self._listened.wait()

    async def start(self) -> None:
        """Listen on the socket path (removing a stale socket left by a crash), with the configured mode."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        _remove_stale_socket(self.path)
        self._closing.clear()
        self._server = await asyncio.start_unix_server(self._serve, path=str(self.path))
        os.chmod(self.path, self.mode)

    def publish(self, message: Mapping[str, Any]) -> None:
        """Queue a message for every client; the oldest queued message of a full queue is dropped."""
        self.publish_encoded(encode(message))

    def publish_encoded(self, line: bytes) -> None:
        """`publish` for a message already encoded by `encode`."""
        self.counters["published"] += 1
        for client in self._clients.values():
            if len(client.queue) == self.queue_size:
                client.dropped += 1
                self.counters["dropped_messages"] += 1
            client.queue.append(line)
            client.wake.set()

    async def close(self) -> None:
        """Disconnect every client, stop listening and remove the socket file."""
        if self._server is not None:
            self._server.close()
        # Each client's task is asked to end rather than cancelled: asyncio's stream callback (Python 3.11) asks a
        # cancelled connection task for its exception, which raises and logs a traceback at every stop.
        self._closing.set()
        tasks = list(self._clients)
        if tasks:
            _, stuck = await asyncio.wait(tasks, timeout=CLOSE_TIMEOUT_S)
            for task in stuck:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
        if self._server is not None:
            await self._server.wait_closed()
            self._server = None
            with contextlib.suppress(FileNotFoundError):
                self.path.unlink()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        if len(self._clients) >= self.max_clients:
            self.counters["refused"] += 1
            # one line saying why before the close, so the client's user is not left guessing at an empty stream
            writer.write(encode(error_message(f"too many clients (max {self.max_clients})")))
            writer.close()
            with contextlib.suppress(OSError):
                await writer.wait_closed()
            return
        client = _Client(collections.deque([self.hello], maxlen=self.queue_size), asyncio.Event())
        client.wake.set()
        self._clients[task] = client
        self._listened.set()
        self.counters["connected"] += 1
        try:
            parts = (
                asyncio.ensure_future(self._send(client, writer)),
                asyncio.ensure_future(_until_eof(reader)),
                asyncio.ensure_future(self._closing.wait()),
            )
            try:
                await asyncio.wait(parts, return_when=asyncio.FIRST_COMPLETED)
            finally:
                for part in parts:
                    part.cancel()
                await asyncio.gather(*parts, return_exceptions=True)
        finally:
            del self._clients[task]
            if not self._clients:
                self._listened.clear()
            writer.close()
            with contextlib.suppress(OSError, asyncio.CancelledError):
                await writer.wait_closed()

    async def _send(self, client: _Client, writer: asyncio.StreamWriter) -> None:
        """Move the client's queue into its socket until it stalls or fails."""
        while True:
            await client.wake.wait()
            client.wake.clear()
            while client.queue:
                writer.write(client.queue.popleft())
            if not writer.transport.get_write_buffer_size():
                continue  # the socket took it all: nothing to wait for (and no timer to arm, many times a second)
            try:
                async with asyncio.timeout(self.stall_s):  # not wait_for: 3.11's can drop a cancellation
                    await writer.drain()
            except TimeoutError:
                self.counters["stalled"] += 1
                log.info("pose client accepted nothing for %.1f s: disconnected", self.stall_s)
                writer.transport.abort()  # close() would wait to flush what it refused to read
                return
            except (ConnectionError, OSError):
                return


async def _until_eof(reader: asyncio.StreamReader) -> None:
    """Read and discard what the client sends until it hangs up."""
    with contextlib.suppress(ConnectionError, OSError):
        while await reader.read(4096):
            pass


def _remove_stale_socket(path: Path) -> None:
    """Remove a socket file nobody listens on; refuse to touch anything else."""
    try:
        info = path.lstat()
    except FileNotFoundError:
        return
    if not stat.S_ISSOCK(info.st_mode):
        raise FileExistsError(f"{path} exists and is not a socket: refusing to replace it")
    probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        probe.connect(str(path))
    except OSError:
        path.unlink(missing_ok=True)  # a crash left it behind
        return
    finally:
        probe.close()
    raise FileExistsError(f"{path}: another process is serving on this socket")
