"""An MCAP file served over Foxglove's WebSocket protocol with the timeline's playback controls (play, pause, speed,
seek), for `robotd replay LOG --view`: a person scrubs to the seconds where the filter went wrong.

Theory of operation. The file's messages are read once into memory (channel, log time, bytes), sorted by log time,
and their channels re-created on a private SDK context with the file's own schemas, so any MCAP robotd wrote plays
back as it was recorded. The server advertises `PlaybackControl` with the file's time range; the SDK calls the
listener from its own thread with each request, which changes the shared state under a lock and answers with the
new state (`did_seek` tells the app to drop what it buffered). `run()` paces the messages in the caller's thread:
every `TICK_S` it moves the playback time by the wall time elapsed times the speed, logs the messages up to it and
broadcasts the time; at the end it says Ended and waits for a seek or for `stop`.
"""

from __future__ import annotations

import bisect
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import foxglove
from foxglove import Context
from foxglove.websocket import (
    Capability,
    PlaybackCommand,
    PlaybackControlRequest,
    PlaybackState,
    PlaybackStatus,
    ServerListener,
    WebSocketServer,
)
from mcap.reader import make_reader

TICK_S = 0.02


@dataclass(slots=True)
class _State:
    """Where playback stands (guarded by the player's lock)."""

    status: PlaybackStatus
    time_ns: int
    index: int  # the next message to send
    speed: float = 1.0


class McapPlayer(ServerListener):
    """Serves one MCAP file with playback controls (see the module docstring)."""

    def __init__(self, path: Path) -> None:
        self._context = Context()
        self._channels: dict[int, foxglove.Channel] = {}
        messages: list[tuple[int, int, bytes]] = []
        with path.open("rb") as stream:
            for schema, channel, message in make_reader(stream).iter_messages(log_time_order=True):
                if channel.id not in self._channels:
                    sdk_schema = (
                        None
                        if schema is None or not schema.name
                        else foxglove.Schema(name=schema.name, encoding=schema.encoding, data=schema.data)
                    )
                    self._channels[channel.id] = foxglove.Channel(
                        channel.topic, schema=sdk_schema, message_encoding=channel.message_encoding,
                        context=self._context,
                    )  # fmt: skip
                messages.append((message.log_time, channel.id, message.data))
        if not messages:
            raise ValueError(f"{path}: no messages to play")
        self._times = [log_time for log_time, _, _ in messages]
        self._messages = messages
        self.start_ns, self.end_ns = self._times[0], self._times[-1]
        self._lock = threading.Lock()
        self._state = _State(PlaybackStatus.Paused, self.start_ns, 0)
        self._server: WebSocketServer | None = None
        self.sent = 0

    def serve(self, host: str, port: int) -> int:
        """Start the server; returns its port."""
        self._server = foxglove.start_server(
            name="robotd replay",
            host=host,
            port=port,
            context=self._context,
            capabilities=[Capability.PlaybackControl, Capability.Time],
            server_listener=self,
            playback_time_range=(self.start_ns, self.end_ns),
        )
        return self._server.port

    def stop(self) -> None:
        """Stop the server."""
        if self._server is not None:
            self._server.stop()
            self._server = None

    # --- the SDK's thread -----------------------------------------------------------------------------------------

    def on_playback_control_request(self, playback_control_request: PlaybackControlRequest) -> PlaybackState | None:
        """Play, pause, change speed, seek; answer with the state that follows."""
        request = playback_control_request
        with self._lock:
            state = self._state
            did_seek = request.seek_time is not None
            if request.seek_time is not None:
                state.time_ns = min(max(request.seek_time, self.start_ns), self.end_ns)
                state.index = bisect.bisect_left(self._times, state.time_ns)
            state.speed = request.playback_speed if request.playback_speed > 0.0 else 1.0
            if request.playback_command == PlaybackCommand.Play:
                at_end = state.index >= len(self._messages)
                state.status = PlaybackStatus.Ended if at_end else PlaybackStatus.Playing
            else:
                state.status = PlaybackStatus.Paused
            return PlaybackState(state.status, state.time_ns, state.speed, did_seek, request.request_id)

    # --- pacing ---------------------------------------------------------------------------------------------------

    def state(self) -> tuple[PlaybackStatus, int, float]:
        """Status, playback time (ns) and speed now."""
        with self._lock:
            return self._state.status, self._state.time_ns, self._state.speed

    def run(self, stop: threading.Event) -> None:
        """Pace the messages until `stop` is set."""
        last = time.monotonic()
        while not stop.wait(TICK_S):
            now = time.monotonic()
            elapsed, last = now - last, now
            self.step(elapsed)

    def step(self, elapsed_s: float) -> None:
        """Move playback on by `elapsed_s` of wall time: send the messages up to the new time, broadcast it."""
        with self._lock:
            state = self._state
            if state.status is not PlaybackStatus.Playing:
                return
            state.time_ns = min(self.end_ns, state.time_ns + round(elapsed_s * state.speed * 1e9))
            end = bisect.bisect_right(self._times, state.time_ns)
            batch = self._messages[state.index : end]
            state.index = end
            ended = end >= len(self._messages)
            if ended:
                state.status = PlaybackStatus.Ended
            time_ns, speed = state.time_ns, state.speed
        for log_time, channel_id, data in batch:
            self._channels[channel_id].log(data, log_time=log_time)
        self.sent += len(batch)
        if self._server is not None:
            self._server.broadcast_time(time_ns)
            if ended:
                self._server.broadcast_playback_state(PlaybackState(PlaybackStatus.Ended, time_ns, speed, False, None))
