"""The `fleet` section of robotd's configuration: the link to an MQTT broker shared by the robots of one map.

Split from robotd.config.model (one section, one job); off by default: a robot alone needs no broker.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from robotd.config.schema import host, in_range, port_number, setting

ROBOT_ID = re.compile(r"[A-Za-z0-9_-]{1,64}")
"""A robot's name in the topic tree: no MQTT wildcards (+, #), no level separator (/), and never `fleet`."""
RESERVED_IDS = frozenset({"fleet"})


def _robot_id(value: str) -> str | None:
    """Empty (only while the link is off), or letters, digits, _ and -, at most 64, not `fleet`."""
    if value == "" or (ROBOT_ID.fullmatch(value) and value not in RESERVED_IDS):
        return None
    return f"must be letters, digits, _ or - (at most 64) and not 'fleet', got {value!r}"


@dataclass(frozen=True, slots=True)
class FleetConfig:
    """The fleet link: pose and status to an MQTT broker under robotd/<robot_id>/, and the fleet stop from it."""

    enabled: bool = setting(False, "Connect to the broker (robot_id and key_file are then required).")
    robot_id: str = setting("", "This robot's name in the topic tree robotd/<robot_id>/.", _robot_id)
    host: str = setting("127.0.0.1", "Host of the MQTT broker.", host)
    port: int = setting(1883, "TCP port of the broker (8883 is the usual one with TLS).", port_number)
    credentials_file: str = setting(
        "", "File holding `username:password` for the broker (one line, mode 0600 or root:robotd 0640); '' for none."
    )
    key_file: str = setting(
        "",
        "File holding the fleet key: the HMAC-SHA256 key that signs fleet stops and releases (as teleop's key file).",
    )
    tls: bool = setting(False, "Connect with TLS, verifying the broker's certificate.")
    ca_file: str = setting("", "CA certificate(s) that sign the broker's certificate; '' for the system's CAs.")
    pose_rate_hz: float = setting(10.0, "Poses published per second (QoS 0).", in_range(0.1, 100.0))
    status_period_s: float = setting(
        1.0, "Seconds between retained status messages (and on every change of the stop).", in_range(0.1, 60.0)
    )
    keepalive_s: int = setting(
        5,
        "MQTT keep-alive: the broker publishes the last will ('offline') this long (x1.5) after the robot goes"
        " silent without closing its connection.",
        in_range(1, 600),
    )
    queue_size: int = setting(
        32,
        "Messages waiting for the broker; when it is slow or away the oldest are dropped and counted, so the"
        " control loop never waits for it.",
        in_range(1, 10_000),
    )
    reconnect_max_s: float = setting(
        5.0, "Longest wait between reconnection attempts (backoff cap).", in_range(0.05, 300.0)
    )
    max_clock_offset_s: float = setting(
        30.0,
        "Refuse a stop or release signed more than this far in the future of our Unix clock (a wrong clock would"
        " otherwise lock out every later release).",
        in_range(0.0, 3600.0, above_low=True),
    )

    def __post_init__(self) -> None:
        if self.enabled and not self.robot_id:
            raise ValueError("robot_id: required when the fleet link is enabled")
        if self.enabled and not self.key_file:
            raise ValueError("key_file: required when the fleet link is enabled (fleet stops must be verified)")
