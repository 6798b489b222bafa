"""The sensor log format (JSON Lines): the interchange for record, replay and evaluation.

One JSON object a line, in arrival order; `t` is the arrival time in seconds on one monotonic clock. The format is
specified in the README ("Sensor log format"). Reading never raises on content: a malformed line is reported with its
line number and skipped, an unknown `type` is counted, so that a log from a newer robotd or a damaged file still
replays everything it can.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

import numpy as np
import numpy.typing as npt

from robotd import logbulk
from robotd.logevents import (
    FORMAT,
    VERSION,
    Command,
    Event,
    IpsFix,
    IpsLost,
    Meta,
    Truth,
    TwistSample,
    Wheels,
    encode,
)


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


@dataclass(frozen=True, slots=True)
class Columns:
    """A log's events as columns: wheel samples and truth as arrays, the rest as objects, and their file order.

    `kinds` holds, per event in file order, WHEELS_KIND, TRUTH_KIND or OTHER_KIND; the n-th event of a kind is row n
    of its column (or others[n]).
    """

    kinds: npt.NDArray[np.int8]
    wheels_t: npt.NDArray[np.float64]
    wheels_ticks: npt.NDArray[np.int64]  # n x 4, FL FR RL RR
    truth: npt.NDArray[np.float64]  # n x 4: t, x, y, theta (NaN when the line had none)
    others: list[Event]

    def others_after(self) -> npt.NDArray[np.int64]:
        """For each of `others`, how many wheel samples come before it in the file."""
        wheels_before = np.cumsum(self.kinds == WHEELS_KIND, dtype=np.int64)
        return np.asarray(wheels_before[self.kinds == OTHER_KIND], dtype=np.int64)

    def __len__(self) -> int:
        return len(self.kinds)

    def time_span(self) -> tuple[float, float]:
        """The times of the first and of the last event in the file (a log without events has none: ValueError)."""
        if not len(self.kinds):
            raise ValueError("no events")
        return self._time_of(0), self._time_of(len(self.kinds) - 1)

    def _time_of(self, position: int) -> float:
        kind = int(self.kinds[position])
        rank = int(np.count_nonzero(self.kinds[: position + 1] == kind)) - 1
        if kind == WHEELS_KIND:
            return float(self.wheels_t[rank])
        if kind == TRUTH_KIND:
            return float(self.truth[rank, 0])
        return self.others[rank].t

    def events(self) -> list[Event]:
        """The events as objects, in file order."""
        wheels = iter(
            [
                Wheels(t, (a, b, c, d))
                for t, (a, b, c, d) in zip(self.wheels_t.tolist(), self.wheels_ticks.tolist(), strict=True)
            ]
        )
        truth = iter([Truth(t, x, y, th) for t, x, y, th in self.truth.tolist()])
        others = iter(self.others)
        sources: dict[int, Iterator[Event]] = {WHEELS_KIND: wheels, TRUTH_KIND: truth, OTHER_KIND: others}
        return [next(sources[kind]) for kind in self.kinds.tolist()]

    @classmethod
    def from_events(cls, events: list[Event]) -> Columns:
        """The columns of a list of events."""
        kinds = [WHEELS_KIND if type(e) is Wheels else TRUTH_KIND if type(e) is Truth else OTHER_KIND for e in events]
        wheels = [e for e in events if type(e) is Wheels]
        truth = [e for e in events if type(e) is Truth]
        return cls(
            np.array(kinds, dtype=np.int8),
            np.array([e.t for e in wheels], dtype=np.float64),
            np.array([e.ticks for e in wheels], dtype=np.int64).reshape(-1, 4),
            np.array([(e.t, e.x, e.y, e.theta) for e in truth], dtype=np.float64).reshape(-1, 4),
            [e for e in events if type(e) is not Wheels and type(e) is not Truth],
        )


WHEELS_KIND, TRUTH_KIND, OTHER_KIND = logbulk.WHEELS_KIND, logbulk.TRUTH_KIND, logbulk.OTHER_KIND


class SensorLog:
    """A parsed log: its meta, its events in file order, and what could not be used.

    The events are held as objects (`events`) or as columns (`columns()`, what replay reads); each view is built from
    the other on first use. `lines` holds the file's line number (from 1) of each event, in file order, for a log
    read from a file (None otherwise, and after `events` is assigned).
    """

    __slots__ = ("_columns", "_events", "lines", "meta", "problems", "unknown_types")

    def __init__(
        self,
        meta: Meta | None = None,
        events: list[Event] | None = None,
        problems: list[str] | None = None,
        unknown_types: Counter[str] | None = None,
        *,
        columns: Columns | None = None,
        lines: npt.NDArray[np.int64] | None = None,
    ) -> None:
        self.meta = meta if meta is not None else Meta()
        self.lines = lines
        self._events = events if events is not None or columns is not None else []
        self._columns = columns
        self.problems = problems if problems is not None else []
        self.unknown_types = unknown_types if unknown_types is not None else Counter()

    @property
    def events(self) -> list[Event]:
        """The events as objects, in file order."""
        if self._events is None:
            assert self._columns is not None
            self._events = self._columns.events()
            self._columns = None  # the list may now be edited: the columns would go stale
        return self._events

    @events.setter
    def events(self, events: list[Event]) -> None:
        self._events, self._columns, self.lines = events, None, None

    def columns(self) -> Columns:
        """The events as columns (built from the objects when the log was made from them)."""
        if self._columns is None:
            return Columns.from_events(self.events)
        return self._columns

    def __repr__(self) -> str:
        return f"SensorLog(meta={self.meta!r}, {len(self.columns().kinds)} events, problems={self.problems!r})"


class _MalformedError(ValueError):
    pass


def _float(obj: dict[str, Any], key: str, default: float | None = None) -> float:
    value = obj.get(key, default)
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise _MalformedError(f"'{key}' must be a number, got {value!r}")
    try:
        return float(value)
    except OverflowError:  # an integer of hundreds of digits
        raise _MalformedError(f"'{key}' is a number beyond any double") from None


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


def _parse_line(line: str) -> Event | Meta | str | None:
    """One line through json.loads: an event, the meta, an unknown type's name, None when blank."""
    if not line.strip():
        return None
    obj = json.loads(line)
    if not isinstance(obj, dict):
        raise _MalformedError("not a JSON object")
    return _decode(obj)


def parse_lines(lines: Iterable[str]) -> SensorLog:
    """Parse the lines of a sensor log; never raises on content."""
    texts = list(lines)
    stripped = [line.removesuffix("\n") for line in texts]
    text = "\n".join(stripped) + "\n" if texts else ""
    if text.count("\n") != len(texts):  # a line holding a newline: keep it one line (it is not a standard one)
        text = "".join(line.replace("\n", "\0") + "\n" for line in stripped)
    # every line ends with a newline here, so the bulk reader sees them all; it reads only ASCII, a lone surrogate
    # just makes the line a non-standard one, read from `texts`
    return _parse(text.encode("utf-8", "surrogatepass"), texts)


def read_log(path: str | Path) -> SensorLog:
    """Read a sensor log file."""
    data = Path(path).read_bytes()
    if b"\r" in data:
        # as a text-mode read does (universal newlines): '\r\n' and a lone '\r' end a line. ASCII bytes decode to
        # themselves and end any invalid UTF-8 sequence, so this commutes with decoding
        data = data.replace(b"\r\n", b"\n").replace(b"\r", b"\n")
    return _parse(data, None)


def _parse(text: bytes, originals: list[str] | None) -> SensorLog:
    """Parse a text of lines: standard lines in bulk (robotd.logbulk), the rest one by one.

    `originals` are the lines as given, each a line of `text` (for json.loads's error positions); None means the lines
    are `text`'s, decoded as UTF-8 with errors replaced, with their newline if they have one.
    """
    bulk = logbulk.parse_standard(text)
    kinds = bulk.kinds
    log = SensorLog()
    extra_others: list[tuple[int, Event]] = []  # events other than fixes, from the per-line reader
    extra_wheels: list[tuple[int, Wheels]] = []
    extra_truth: list[tuple[int, Truth]] = []
    ends = bulk.line_ends
    for index in np.flatnonzero(kinds == logbulk.PER_LINE).tolist():
        kinds[index] = logbulk.NO_EVENT  # unless it decodes to an event
        if originals is not None:
            line = originals[index]
        else:
            start, end = int(ends[index - 1]) + 1 if index else 0, int(ends[index])
            line = text[start:end].decode("utf-8", "replace") + ("\n" if end < len(text) else "")
        try:
            item = _parse_line(line)
            if isinstance(item, Wheels) and not all(-(2**63) <= n < 2**63 for n in item.ticks):
                raise _MalformedError("'ticks' must be 64-bit integers")
        except (json.JSONDecodeError, _MalformedError) as error:
            log.problems.append(f"line {index + 1}: {error}")
            continue
        except ValueError:  # json reads integers with int(), which refuses more than 4300 digits
            log.problems.append(f"line {index + 1}: a number too long to read (over 4300 digits)")
            continue
        except RecursionError:  # json's decoder recurses once per level of nesting
            log.problems.append(f"line {index + 1}: JSON nested too deeply")
            continue
        if item is None:
            continue
        if isinstance(item, str):
            log.unknown_types[item] += 1
        elif isinstance(item, Meta):
            log.meta = item
        elif isinstance(item, Wheels):
            kinds[index] = WHEELS_KIND
            extra_wheels.append((index, item))
        elif isinstance(item, Truth):
            kinds[index] = TRUTH_KIND
            extra_truth.append((index, item))
        else:
            kinds[index] = OTHER_KIND
            extra_others.append((index, item))
    others = _others(kinds, bulk, extra_others)
    wheels_t, wheels_ticks, truth = bulk.wheels_t, bulk.wheels_ticks, bulk.truth
    if extra_wheels:
        wheels_t, wheels_ticks = logbulk.merge_in_order(
            kinds,
            WHEELS_KIND,
            [i for i, _ in extra_wheels],
            (wheels_t, np.array([e.t for _, e in extra_wheels])),
            (wheels_ticks, np.array([e.ticks for _, e in extra_wheels], dtype=np.int64)),
        )
    if extra_truth:
        (truth,) = logbulk.merge_in_order(
            kinds,
            TRUTH_KIND,
            [i for i, _ in extra_truth],
            (truth, np.array([(e.t, e.x, e.y, e.theta) for _, e in extra_truth])),
        )
    is_event = kinds >= 0
    columns = Columns(kinds[is_event], wheels_t, wheels_ticks, truth, others)
    lines = np.flatnonzero(is_event).astype(np.int64) + 1
    return SensorLog(log.meta, None, log.problems, log.unknown_types, columns=columns, lines=lines)


def _others(kinds: npt.NDArray[np.int8], bulk: logbulk.Bulk, extra: list[tuple[int, Event]]) -> list[Event]:
    """The bulk-read fixes and twists and the other events read line by line, in file order (their lines become
    OTHER)."""
    fix_lines = np.flatnonzero(kinds == logbulk.IPS_LINE)
    twist_lines = np.flatnonzero(kinds == logbulk.TWIST_LINE)
    kinds[fix_lines] = OTHER_KIND
    kinds[twist_lines] = OTHER_KIND
    events = _fixes(bulk.ips.tolist())
    if not len(twist_lines) and not extra:
        return events
    events += _twists(bulk.twists.tolist())
    events += [event for _, event in extra]
    lines = np.concatenate((fix_lines, twist_lines, np.array([index for index, _ in extra], dtype=np.intp)))
    return [events[i] for i in np.argsort(lines, kind="stable").tolist()]


# IpsFix's fields' slots, in order: a frozen dataclass's __init__ sets each field through object.__setattr__, which
# costs twice as much as filling the slots themselves; the fixes of a log are many
_FIX_SLOTS = tuple(getattr(IpsFix, field.name).__set__ for field in dataclasses.fields(IpsFix))


def _fixes(rows: list[list[float]]) -> list[Event]:
    """IpsFix events of (t, x, y, z, t_meas) rows, as IpsFix(*row) builds them."""
    set_t, set_x, set_y, set_z, set_t_meas = _FIX_SLOTS
    new = object.__new__
    events: list[Event] = []
    for t, x, y, z, t_meas in rows:
        fix = new(IpsFix)
        set_t(fix, t)
        set_x(fix, x)
        set_y(fix, y)
        set_z(fix, z)
        set_t_meas(fix, t_meas)
        events.append(fix)
    return events


_TWIST_SLOTS = tuple(getattr(TwistSample, field.name).__set__ for field in dataclasses.fields(TwistSample))


def _twists(rows: list[list[float]]) -> list[Event]:
    """TwistSample events of (t, vx, vy, wz) rows, as TwistSample(*row) builds them (see _FIX_SLOTS)."""
    set_t, set_vx, set_vy, set_wz = _TWIST_SLOTS
    new = object.__new__
    events: list[Event] = []
    for t, vx, vy, wz in rows:
        twist = new(TwistSample)
        set_t(twist, t)
        set_vx(twist, vx)
        set_vy(twist, vy)
        set_wz(twist, wz)
        events.append(twist)
    return events


def iter_events(log: SensorLog, *types: type[Event]) -> Iterator[Event]:
    """The log's events of the given types, in order."""
    return (event for event in log.events if isinstance(event, types))


__all__ = [
    "FORMAT",
    "OTHER_KIND",
    "TRUTH_KIND",
    "VERSION",
    "WHEELS_KIND",
    "Columns",
    "Command",
    "Event",
    "IpsFix",
    "IpsLost",
    "LogWriter",
    "Meta",
    "SensorLog",
    "Truth",
    "TwistSample",
    "Wheels",
    "encode",
    "iter_events",
    "parse_lines",
    "read_log",
]
