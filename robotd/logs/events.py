"""The sensor log's records: one typed msgspec Struct per line type, tagged by the line's "type".

The format is specified in the README ("Sensor log format"); robotd.logs.sensorlog writes and reads whole logs. Decoding
checks every field's type (ticks are 64-bit integers, numbers finite: JSON has no NaN or infinity, and a number too
large for a double is refused); a field a record does not know is ignored, so that a newer robotd's lines still read.
"""

from __future__ import annotations

import math
from typing import Annotated, Any

import msgspec

FORMAT = "robotd-log"
VERSION = 1
DECIMALS = 6  # microseconds and micrometres, below every sensor's resolution; keeps logs short and stable

Tick = Annotated[int, msgspec.Meta(ge=-(2**63), le=2**63 - 1)]

# The events are gc=False: they hold numbers only, never a reference cycle, so the cyclic garbage collector need not
# walk a log's hundreds of thousands of them (a fifth of a replay's time otherwise).


class Meta(msgspec.Struct, frozen=True, tag="meta"):
    """The log's header: robot geometry overrides (all optional), a free-text source, the format and its version."""

    robot: dict[str, Any] = msgspec.field(default_factory=dict)
    source: str = ""
    format: str = FORMAT
    version: int = VERSION


WHEEL_NAMES = ("front-left", "front-right", "rear-left", "rear-right")  # the order of Wheels.ticks


class Wheels(msgspec.Struct, frozen=True, gc=False, tag="wheels"):
    """Cumulative decoded encoder counts, wheel order FL FR RL RR."""

    t: float
    ticks: tuple[Tick, Tick, Tick, Tick]


class TwistSample(msgspec.Struct, frozen=True, gc=False, tag="twist"):
    """A measured body velocity (m/s, rad/s): the alternative to wheel ticks."""

    t: float
    vx: float
    vy: float
    wz: float


class IpsFix(msgspec.Struct, frozen=True, gc=False, tag="ips"):
    """A valid IPS fix of the beacon (m); t_meas is when it was measured, NaN when the line has none (the fix's delay
    is unknown: the filter learns it; `stated_t` is then its arrival)."""

    t: float
    x: float
    y: float
    z: float = 0.0
    t_meas: float = math.nan  # JSON has no NaN: absent from the line

    @property
    def timed(self) -> bool:
        """Whether the fix carries its measurement time."""
        return not math.isnan(self.t_meas)

    @property
    def stated_t(self) -> float:
        """Its measurement time when it has one, else its arrival time."""
        return self.t if math.isnan(self.t_meas) else self.t_meas


class _UntimedFix(msgspec.Struct, frozen=True, gc=False, tag="ips"):
    """How an IpsFix without a measurement time is written: the line leaves t_meas out."""

    t: float
    x: float
    y: float
    z: float


class IpsLost(msgspec.Struct, frozen=True, gc=False, tag="ips_lost"):
    """A position packet flagged "coordinates unavailable"."""

    t: float


class Truth(msgspec.Struct, frozen=True, gc=False, tag="truth", omit_defaults=True):
    """Ground truth of the robot's centre, for evaluation only; theta NaN (left out of the line) when unknown."""

    t: float
    x: float
    y: float
    theta: float = math.nan


class Command(msgspec.Struct, frozen=True, gc=False, tag="cmd"):
    """A teleop command (body frame)."""

    t: float
    vx: float
    vy: float
    wz: float


Event = Wheels | TwistSample | IpsFix | IpsLost | Truth | Command
Record = Event | Meta
TYPES = frozenset(("meta", "wheels", "twist", "ips", "ips_lost", "truth", "cmd"))
"""The line types this version reads."""

_encoder = msgspec.json.Encoder()


def rounded(record: Record) -> Record:
    """The record with its numbers rounded to DECIMALS (a truth without heading keeps none)."""
    if isinstance(record, Meta | Wheels | IpsLost):
        return record if isinstance(record, Meta) else msgspec.structs.replace(record, t=round(record.t, DECIMALS))
    values = [round(value, DECIMALS) for value in msgspec.structs.astuple(record)]
    if isinstance(record, Truth) and not math.isfinite(record.theta):
        return Truth(values[0], values[1], values[2])
    return type(record)(*values)


def encode(record: Record) -> str:
    """One record as its JSON line (without the newline), numbers rounded to DECIMALS."""
    line = rounded(record)
    if type(line) is IpsFix and math.isnan(line.t_meas):
        return _encoder.encode(_UntimedFix(line.t, line.x, line.y, line.z)).decode()
    return _encoder.encode(line).decode()


__all__ = [
    "DECIMALS",
    "FORMAT",
    "TYPES",
    "VERSION",
    "WHEEL_NAMES",
    "Command",
    "Event",
    "IpsFix",
    "IpsLost",
    "Meta",
    "Record",
    "Truth",
    "TwistSample",
    "Wheels",
    "encode",
    "rounded",
]
