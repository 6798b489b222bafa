"""The sensor log's records: one frozen dataclass per line type, and each one's JSON line.

The format is specified in the README ("Sensor log format"); robotd.logfile writes and reads whole logs.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Any

FORMAT = "robotd-log"
VERSION = 1


@dataclass(frozen=True, slots=True)
class Meta:
    """The log's header: robot geometry overrides (all optional) and a free-text source."""

    robot: dict[str, Any] = field(default_factory=dict)
    source: str = ""


@dataclass(frozen=True, slots=True)
class Wheels:
    """Cumulative decoded encoder counts, wheel order FL FR RL RR."""

    t: float
    ticks: tuple[int, int, int, int]


@dataclass(frozen=True, slots=True)
class TwistSample:
    """A measured body velocity (m/s, rad/s): the alternative to wheel ticks."""

    t: float
    vx: float
    vy: float
    wz: float


@dataclass(frozen=True, slots=True)
class IpsFix:
    """A valid IPS fix of the beacon (m); t_meas is when it was measured."""

    t: float
    x: float
    y: float
    z: float
    t_meas: float


@dataclass(frozen=True, slots=True)
class IpsLost:
    """A position packet flagged "coordinates unavailable"."""

    t: float


@dataclass(frozen=True, slots=True)
class Truth:
    """Ground truth of the robot's centre, for evaluation only."""

    t: float
    x: float
    y: float
    theta: float


@dataclass(frozen=True, slots=True)
class Command:
    """A teleop command (body frame)."""

    t: float
    vx: float
    vy: float
    wz: float


Event = Wheels | TwistSample | IpsFix | IpsLost | Truth | Command


def _num(value: float) -> float:
    # Six decimals: microseconds and micrometres, below every sensor's resolution; keeps logs short and stable.
    return round(value, 6)


def encode(event: Event | Meta) -> str:
    """One event as its JSON line (without the newline)."""
    match event:
        case Meta():
            obj: dict[str, Any] = {
                "type": "meta",
                "format": FORMAT,
                "version": VERSION,
                "robot": event.robot,
                "source": event.source,
            }
        case Wheels():
            obj = {"t": _num(event.t), "type": "wheels", "ticks": list(event.ticks)}
        case TwistSample():
            obj = {
                "t": _num(event.t),
                "type": "twist",
                "vx": _num(event.vx),
                "vy": _num(event.vy),
                "wz": _num(event.wz),
            }
        case IpsFix():
            obj = {
                "t": _num(event.t),
                "type": "ips",
                "x": _num(event.x),
                "y": _num(event.y),
                "z": _num(event.z),
                "t_meas": _num(event.t_meas),
            }
        case IpsLost():
            obj = {"t": _num(event.t), "type": "ips_lost"}
        case Truth():
            obj = {
                "t": _num(event.t),
                "type": "truth",
                "x": _num(event.x),
                "y": _num(event.y),
            }
            if math.isfinite(event.theta):  # truth without heading omits it (JSON has no NaN)
                obj["theta"] = _num(event.theta)
        case Command():
            obj = {"t": _num(event.t), "type": "cmd", "vx": _num(event.vx), "vy": _num(event.vy), "wz": _num(event.wz)}
    return json.dumps(obj, separators=(", ", ": "))
