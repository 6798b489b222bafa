"""The sensor log format (JSON Lines): the interchange for record, replay and evaluation.

One JSON object a line, in arrival order; `t` is the arrival time in seconds on one monotonic clock. The format is
specified in the README ("Sensor log format"). Reading never raises on content: a malformed line is reported with its
line number and skipped, an unknown `type` is counted, so that a log from a newer robotd or a damaged file still
replays everything it can.
"""

from __future__ import annotations

import json
import math
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

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


class LogWriter:
    """Writes a sensor log: the meta line first, then one line per event, flushed as it goes."""

    def __init__(self, stream: TextIO, meta: Meta) -> None:
        self._stream = stream
        self._stream.write(encode(meta) + "\n")

    def write(self, event: Event) -> None:
        """Append one event."""
        self._stream.write(encode(event) + "\n")

    def flush(self) -> None:
        """Push buffered lines to the file."""
        self._stream.flush()


@dataclass(slots=True)
class SensorLog:
    """A parsed log: its meta, its events in file order, and what could not be used."""

    meta: Meta = field(default_factory=Meta)
    events: list[Event] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    unknown_types: Counter[str] = field(default_factory=Counter)


class _MalformedError(ValueError):
    pass


def _float(obj: dict[str, Any], key: str, default: float | None = None) -> float:
    value = obj.get(key, default)
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise _MalformedError(f"'{key}' must be a number, got {value!r}")
    return float(value)


def _decode(obj: dict[str, Any]) -> Event | Meta | str:
    """An event, the meta, or the name of an unknown type."""
    kind = obj.get("type")
    if kind == "meta":
        robot = obj.get("robot", {})
        if not isinstance(robot, dict):
            raise _MalformedError("'robot' must be an object")
        return Meta(robot=robot, source=str(obj.get("source", "")))
    if not isinstance(kind, str):
        raise _MalformedError("missing 'type'")
    if kind not in {"wheels", "twist", "ips", "ips_lost", "truth", "cmd"}:
        return kind
    t = _float(obj, "t")
    if kind == "wheels":
        ticks = obj.get("ticks")
        if (
            not isinstance(ticks, list)
            or len(ticks) != 4
            or not all(isinstance(n, int) and not isinstance(n, bool) for n in ticks)
        ):
            raise _MalformedError("'ticks' must be a list of 4 integers")
        return Wheels(t, (ticks[0], ticks[1], ticks[2], ticks[3]))
    if kind == "twist":
        return TwistSample(t, _float(obj, "vx"), _float(obj, "vy"), _float(obj, "wz"))
    if kind == "ips":
        return IpsFix(t, _float(obj, "x"), _float(obj, "y"), _float(obj, "z", 0.0), _float(obj, "t_meas", t))
    if kind == "ips_lost":
        return IpsLost(t)
    if kind == "truth":
        return Truth(t, _float(obj, "x"), _float(obj, "y"), _float(obj, "theta", math.nan))
    return Command(t, _float(obj, "vx"), _float(obj, "vy"), _float(obj, "wz"))


def parse_lines(lines: Iterable[str]) -> SensorLog:
    """Parse the lines of a sensor log; never raises on content."""
    log = SensorLog()
    for number, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        try:
            obj = json.loads(line)
            if not isinstance(obj, dict):
                raise _MalformedError("not a JSON object")
            item = _decode(obj)
        except (json.JSONDecodeError, _MalformedError) as error:
            log.problems.append(f"line {number}: {error}")
            continue
        if isinstance(item, str):
            log.unknown_types[item] += 1
        elif isinstance(item, Meta):
            log.meta = item
        else:
            log.events.append(item)
    return log


def read_log(path: str | Path) -> SensorLog:
    """Read a sensor log file."""
    with open(path, encoding="utf-8", errors="replace") as stream:
        return parse_lines(stream)


def iter_events(log: SensorLog, *types: type[Event]) -> Iterator[Event]:
    """The log's events of the given types, in order."""
    return (event for event in log.events if isinstance(event, types))
