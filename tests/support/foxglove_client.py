"""A client of Foxglove's WebSocket protocol (`foxglove.sdk.v1`) for tests, on the `websockets` package.

It speaks what a viewer does to watch: reads `serverInfo` and `advertise`, subscribes to topics, and decodes each
binary Message Data frame (opcode 1: u32 subscription id, u64 receive time in ns, then the payload, little-endian)
with the channel's schema: protobuf through the advertised FileDescriptorSet, JSON as is. It does not model client
publishing, services, parameters or assets.
"""

from __future__ import annotations

import asyncio
import base64
import json
import struct
from dataclasses import dataclass
from typing import Any

import websockets
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from google.protobuf.message import Message

SUBPROTOCOL = "foxglove.sdk.v1"
MESSAGE_DATA = 1
HEADER = struct.Struct("<BIQ")


@dataclass(frozen=True, slots=True)
class Received:
    """One decoded message: its topic, the server's log time (ns) and the message (protobuf or a JSON dict)."""

    topic: str
    log_time: int
    message: Any


class FoxgloveClient:
    """A connected viewer (use `async with FoxgloveClient.connect(port) as client`)."""

    def __init__(self, ws: websockets.ClientConnection) -> None:
        self.ws = ws
        self.server_info: dict[str, Any] = {}
        self.channels: dict[str, dict[str, Any]] = {}  # by topic
        self.text: list[dict[str, Any]] = []  # every JSON message from the server
        self.other_binary: list[bytes] = []  # every binary message that is not Message Data
        self._subscriptions: dict[int, dict[str, Any]] = {}
        self._decoders: dict[int, type[Message] | None] = {}

    @classmethod
    async def open(cls, port: int) -> FoxgloveClient:
        """Connect and read the server's hello."""
        ws = await websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[websockets.Subprotocol(SUBPROTOCOL)])
        return cls(ws)

    async def close(self) -> None:
        """Close the connection."""
        await self.ws.close()

    async def wait_for_topics(self, topics: set[str], timeout_s: float = 10.0) -> None:
        """Read until every topic is advertised."""
        async with asyncio.timeout(timeout_s):
            while not topics <= self.channels.keys():
                await self._read_one()

    async def subscribe(self, topics: list[str]) -> None:
        """Subscribe to these topics (advertised first)."""
        await self.wait_for_topics(set(topics))
        subscriptions = []
        for topic in topics:
            sub_id = len(self._subscriptions) + 1
            channel = self.channels[topic]
            self._subscriptions[sub_id] = channel
            self._decoders[sub_id] = _decoder(channel)
            subscriptions.append({"id": sub_id, "channelId": channel["id"]})
        await self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))

    async def receive(self, timeout_s: float = 10.0) -> Received:
        """The next message on a subscription."""
        async with asyncio.timeout(timeout_s):
            while True:
                received = await self._read_one()
                if received is not None:
                    return received

    async def collect(self, count: dict[str, int], timeout_s: float = 20.0) -> dict[str, list[Received]]:
        """Messages until each topic of `count` has at least that many."""
        got: dict[str, list[Received]] = {topic: [] for topic in count}
        async with asyncio.timeout(timeout_s):
            while any(len(got[topic]) < n for topic, n in count.items()):
                received = await self.receive(timeout_s)
                got.setdefault(received.topic, []).append(received)
        return got

    async def _read_one(self) -> Received | None:
        frame = await self.ws.recv()
        if isinstance(frame, str):
            message = json.loads(frame)
            self.text.append(message)
            if message["op"] == "serverInfo":
                self.server_info = message
            elif message["op"] == "advertise":
                for channel in message["channels"]:
                    self.channels[channel["topic"]] = channel
            return None
        if frame[0] != MESSAGE_DATA:  # Time, Playback State...: kept, not decoded
            self.other_binary.append(bytes(frame))
            return None
        _, sub_id, log_time = HEADER.unpack_from(frame)
        if sub_id not in self._subscriptions:
            return None
        payload = frame[HEADER.size :]
        decoder = self._decoders[sub_id]
        message = json.loads(payload) if decoder is None else decoder.FromString(payload)
        return Received(self._subscriptions[sub_id]["topic"], log_time, message)


def _decoder(channel: dict[str, Any]) -> type[Message] | None:
    """The protobuf class of a protobuf channel; None for JSON."""
    if channel["encoding"] == "json":
        return None
    assert channel["encoding"] == "protobuf", channel
    return protobuf_class(channel["schemaName"], base64.b64decode(channel["schema"]))


def protobuf_class(name: str, file_descriptor_set: bytes) -> type[Message]:
    """The protobuf class of message `name` from a serialised FileDescriptorSet (a channel's or an MCAP schema's)."""
    pool = descriptor_pool.DescriptorPool()
    for file in descriptor_pb2.FileDescriptorSet.FromString(file_descriptor_set).file:
        pool.Add(file)
    decoder: type[Message] = message_factory.GetMessageClass(pool.FindMessageTypeByName(name))
    return decoder


PLAYBACK_CONTROL_REQUEST = 3  # the client's binary opcode


def playback_request(play: bool, speed: float, seek_ns: int | None, request_id: str) -> bytes:
    """A Playback Control Request: command (0 play, 1 pause), speed f32, had-seek u8, seek time u64, request id."""
    rid = request_id.encode()
    return (
        struct.pack(
            "<BBfBQI", PLAYBACK_CONTROL_REQUEST, 0 if play else 1, speed, seek_ns is not None, seek_ns or 0, len(rid)
        )
        + rid
    )
