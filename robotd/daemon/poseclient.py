"""The client side of the pose socket: connect, then read its JSON Lines as messages with their arrival times.

One client for every reader of the socket (`robotd pose`, the demo's recorder, the doctor, the benchmark and the
tests), so that a change of the protocol is made once. Blocking sockets: its readers are threads and command-line
programs, not the daemon's event loop.
"""

from __future__ import annotations

import json
import socket
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

from robotd.daemon.posesock import PROTOCOL, PROTOCOL_VERSION


@dataclass(frozen=True, slots=True)
class PoseSocketMessage:
    """One line of the pose socket: when it arrived (monotonic s), its text, and the object it holds (None when the
    line is not a JSON object)."""

    arrived: float
    line: str
    message: dict[str, Any] | None

    @property
    def kind(self) -> str | None:
        """The message's `type` (hello, pose, status, error), or None."""
        kind = None if self.message is None else self.message.get("type")
        return kind if isinstance(kind, str) else None


def decode(line: str, arrived: float) -> PoseSocketMessage:
    """A line of the pose socket as a message; a line that is not a JSON object keeps its text with no message."""
    try:
        value = json.loads(line)
    except ValueError:
        value = None
    return PoseSocketMessage(arrived, line, value if isinstance(value, dict) else None)


def unexpected_hello(message: dict[str, Any]) -> str | None:
    """Why a hello message is not the protocol this client speaks, or None when it is."""
    if message.get("protocol") != PROTOCOL or message.get("version") != PROTOCOL_VERSION:
        return f"unexpected protocol {message.get('protocol')!r} version {message.get('version')!r}"
    return None


def connect(path: str, timeout_s: float | None = None) -> socket.socket:
    """A connected stream socket to the pose socket at `path` (OSError when nobody accepts there); `timeout_s` bounds
    every later read too."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        sock.settimeout(timeout_s)
        sock.connect(path)
    except OSError:
        sock.close()
        raise
    return sock


def accepts(path: str) -> bool:
    """Whether the pose socket at `path` accepts a connection now (its file appears at bind, a moment before the
    daemon listens: waiting for the file alone lets a busy machine refuse the first client)."""
    try:
        connect(path).close()
    except OSError:
        return False
    return True


def messages(sock: socket.socket) -> Iterator[PoseSocketMessage]:
    """Every line the daemon sends on `sock`, until it hangs up (or the socket is shut down)."""
    with sock.makefile("r", encoding="utf-8", newline="\n") as stream:
        for line in stream:
            yield decode(line, time.monotonic())


class LineSplitter:
    """Bytes received in pieces (from a non-blocking socket) to whole pose-socket messages."""

    def __init__(self) -> None:
        self._partial = bytearray()

    def feed(self, data: bytes, arrived: float) -> list[PoseSocketMessage]:
        """The messages completed by `data`; a partial last line waits for the next piece."""
        self._partial += data
        *lines, rest = self._partial.split(b"\n")
        self._partial[:] = rest
        return [decode(line.decode("utf-8", "replace") + "\n", arrived) for line in lines]
