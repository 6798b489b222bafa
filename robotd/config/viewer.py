"""The `viewer` section of robotd's configuration: the live Foxglove view (robotd.viz)."""

from __future__ import annotations

from dataclasses import dataclass

from robotd.config.schema import host, in_range, setting


@dataclass(frozen=True, slots=True)
class ViewerConfig:
    """The live view: Foxglove's WebSocket protocol served by the daemon (off on the robot, on in `robotd sim`)."""

    enabled: bool = setting(
        False,
        "Serve the live view. Off by default: on the robot, turn it on for a session (it costs a little CPU while a"
        " viewer is connected, and anyone who reaches the port sees the robot: nothing can be sent back).",
    )
    host: str = setting(
        "127.0.0.1",
        "Address to listen on; loopback by default (reach it through an SSH tunnel: ssh -L 8765:127.0.0.1:8765 pi).",
        host,
    )
    port: int = setting(8765, "TCP port of the WebSocket server (Foxglove's default, 8765); 0 picks a free one.",
                        in_range(0, 65535))  # fmt: skip
    queue: int = setting(
        4096,
        "Items the daemon may hand to the publishing thread before it drops (and counts) the newest: about 20 s of"
        " the daemon's output.",
        in_range(16, 1_000_000),
    )
    client_backlog: int = setting(
        256,
        "Messages buffered per connected viewer; a slow viewer loses the oldest, never the daemon's time.",
        in_range(16, 100_000),
    )
    trail_s: float = setting(
        120.0, "How far back the trails of the fused and odometry-only poses reach, in seconds.", in_range(1.0, 3600.0)
    )
    trail_rate_hz: float = setting(
        2.0, "How often the trails are sent (each is up to a few hundred poses).", in_range(0.1, 20.0)
    )
