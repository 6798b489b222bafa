"""What no sensor can produce, found in a decoded sensor log before it is replayed.

Theory of operation. The reader (robotd.logs.sensorlog) skips the lines that are not the format; these checks are on the
values of the events it decoded, so they hold whatever the reader is. A bad event is skipped and reported with its
line, as the reader reports its lines; only a log that cannot be replayed as a whole is refused (LogRefusedError):
- a number that is not finite (Python's json reads Infinity and NaN) or beyond what it measures can be (LIMITS) is a
  bad line; a missing truth heading (NaN) is the format's "no heading", not a fault;
- a time (`t`, or a fix's `t_meas`) beyond MAX_TIME_S either side of zero is a bad line: up to 2^53 microseconds a
  double still holds a microsecond, which covers monotonic clocks and Unix time; where a log's times start does not
  matter (negative, zero or Unix time replay alike);
- a wheel counter that wraps (16 or 32 bits) is unwrapped, and noted (robotd.logs.counters);
- a wheel sample whose counts moved, since the previous good sample, faster than MAX_WHEEL_RAD_S for the time
  between them is a bad line (a glitch or a corrupted count; no motor turns a wheel at 1600 turns a second);
- times that go backwards refuse the whole log, with both lines: a sensor log is in arrival order, which is what
  makes its replay causal and the same as the daemon's run. Sorting it would invent an order no filter saw (a fix
  fused before the odometry it arrived after), so it is left to the user who knows why the file is out of order (a
  merge of several recordings): `in_time_order`, which `robotd replay --sort` and `robotd tune --sort` ask for;
- a log with no event left is refused ("no events").
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from robotd.logs import counters
from robotd.logs.counters import WheelSamples
from robotd.logs.events import WHEEL_NAMES
from robotd.logs.sensorlog import Command, Event, IpsFix, SensorLog, Truth, TwistSample, Wheels

MAX_TIME_S = 2.0**53 * 1e-6  # 9.0e9 s (285 years): beyond, a double no longer holds a microsecond
MAX_WHEEL_RAD_S = 1e4  # ~1600 turns a second: a hundred times any robot's wheel, far below a corrupted count
MIN_STEP_S = 1e-3  # two samples closer than this (or at the same time) may be this far apart in counts
MAX_POSITION_M = 1e7  # Marvelmind's int32 millimetres end at ±2147 km; a map is far smaller
MAX_SPEED_MPS = 1e3
LIMITS = {
    "t": MAX_TIME_S,
    "t_meas": MAX_TIME_S,
    "x": MAX_POSITION_M,
    "y": MAX_POSITION_M,
    "z": MAX_POSITION_M,
    "theta": 1e6,  # rad: a heading wound a hundred thousand times round still means something; beyond, noise
    "vx": MAX_SPEED_MPS,
    "vy": MAX_SPEED_MPS,
    "wz": MAX_WHEEL_RAD_S,
}
UNITS = {"t": "s", "t_meas": "s", "x": "m", "y": "m", "z": "m", "theta": "rad", "vx": "m/s", "vy": "m/s", "wz": "rad/s"}


class LogRefusedError(ValueError):
    """The log cannot be replayed as a whole; the message says why, with the line where it matters, and `problems`
    lists the bad events found before (as check returns them)."""

    def __init__(self, message: str, problems: list[str]) -> None:
        super().__init__(message)
        self.problems = problems


class Checked(NamedTuple):
    """A checked log: the log to replay, one problem ("line N: ...") per event skipped, and one note ("line N: ...")
    per repair that lost nothing (a wheel counter unwrapped)."""

    log: SensorLog
    problems: list[str]
    notes: list[str]


def check(log: SensorLog, counts_per_rev: int) -> Checked:
    """The log without its bad events and with its wrapped wheel counters unwrapped (robotd.logs.counters), what was
    skipped and what was repaired; LogRefusedError when its times go backwards or no event is left."""
    events = log.events
    count = len(events)
    lines = log.lines if len(log.lines) == count else None
    where = _Where(lines)
    times = np.fromiter((event.t for event in events), dtype=np.float64, count=count)
    bad: dict[int, str] = {}
    _check_values(events, times, bad)
    keep = np.ones(count, dtype=np.bool_)
    keep[list(bad)] = False
    backwards = _backwards(times, keep, where)
    if backwards is not None:
        raise LogRefusedError(backwards, _problems(bad, where))
    events, wheels, unwrapped = counters.unwrap(events, _wheel_samples(events, times, keep), counts_per_rev)
    notes = [f"{where(index)}: {note}" for index, note in unwrapped]
    _check_wheels(wheels, counts_per_rev, bad)
    keep[list(bad)] = False
    problems = _problems(bad, where)
    if not keep.any():
        raise LogRefusedError("no events", problems)
    if not bad and not unwrapped:
        return Checked(log, problems, notes)
    kept = keep.tolist()
    checked = SensorLog(
        log.meta,
        [event for event, ok in zip(events, kept, strict=True) if ok],
        [*log.problems, *problems],
        log.unknown_types,
        [line for line, ok in zip(lines, kept, strict=True) if ok] if lines is not None else [],
    )
    return Checked(checked, problems, notes)


def _problems(bad: dict[int, str], where: _Where) -> list[str]:
    return [f"{where(index)}: {bad[index]}" for index in sorted(bad)]


class _Where:
    """Names an event by its line in the file (or by its rank, for a log that was not read from one)."""

    def __init__(self, lines: list[int] | None) -> None:
        self.lines = lines

    def __call__(self, index: int) -> str:
        return f"line {self.lines[index]}" if self.lines is not None else f"event {index + 1}"


def _check_values(events: list[Event], times: npt.NDArray[np.float64], bad: dict[int, str]) -> None:
    """Numbers that are not finite or beyond LIMITS, times beyond MAX_TIME_S."""
    for index in np.flatnonzero(~(np.abs(times) <= MAX_TIME_S)).tolist():  # (NaN compares False)
        bad[index] = _out_of_bounds("t", float(times[index]))
    for index, event in enumerate(events):
        # wheel samples carry no numbers of their own to bound (their counts are checked as a track): most of a log
        if type(event) is not Wheels and index not in bad and (problem := _event_problem(event)) is not None:
            bad[index] = problem


def _event_problem(event: Event) -> str | None:
    """What is wrong with a fix, twist or command's numbers (None when nothing)."""
    named: dict[str, float]
    if type(event) is IpsFix:
        named = {"x": event.x, "y": event.y, "z": event.z}
        if not math.isnan(event.t_meas):  # (NaN: the line has no measurement time, not a fault)
            named["t_meas"] = event.t_meas
    elif type(event) is Truth:
        # (a truth without heading has theta NaN: the format's "none", not a fault)
        named = (
            {"x": event.x, "y": event.y}
            if math.isnan(event.theta)
            else {"x": event.x, "y": event.y, "theta": event.theta}
        )
    elif type(event) is TwistSample or type(event) is Command:
        named = {"vx": event.vx, "vy": event.vy, "wz": event.wz}
    else:
        return None
    for name, value in named.items():
        if not abs(value) <= LIMITS[name]:  # (NaN compares False)
            return _out_of_bounds(name, value)
    return None


def _out_of_bounds(name: str, value: float) -> str:
    what = "a finite number" if not math.isfinite(value) else f"within ±{LIMITS[name]:g} {UNITS[name]}"
    return f"'{name}' = {value!r} is not {what}"


def _backwards(times: npt.NDArray[np.float64], keep: npt.NDArray[np.bool_], where: _Where) -> str | None:
    """Where the first kept event is earlier than the kept one before it (None when the times never go back)."""
    kept = np.flatnonzero(keep)
    back = np.flatnonzero(np.diff(times[kept]) < 0)
    if not len(back):
        return None
    before, after = int(kept[back[0]]), int(kept[back[0] + 1])
    return (
        f"{where(after)}: time goes backwards, t = {times[after]:.6f} s after t = {times[before]:.6f} s on "
        f"{where(before)}: a sensor log is in arrival order (is it a merge of logs? --sort takes it in time order)"
    )


def in_time_order(log: SensorLog) -> tuple[SensorLog, int]:
    """The log's events in the order of their times (stable: events at one time keep their file order, a time that is
    not a number last, where the check skips it) and how many came after a later one, for a log its user knows to be
    a merge of recordings; never taken by default (see the module docstring)."""
    events = log.events
    times = [event.t for event in events]
    order = sorted(range(len(events)), key=lambda i: (times[i] != times[i], times[i]))  # (NaN: not equal to itself)
    late, newest = 0, -math.inf
    for t in times:
        late += t < newest
        newest = max(newest, t)
    if not late:
        return log, 0
    lines = [log.lines[i] for i in order] if len(log.lines) == len(events) else []
    return SensorLog(log.meta, [events[i] for i in order], log.problems, log.unknown_types, lines), late


def _wheel_samples(events: list[Event], times: npt.NDArray[np.float64], keep: npt.NDArray[np.bool_]) -> WheelSamples:
    """The kept wheel samples as arrays, once for the unwrap and the jump check."""
    rows = [i for i, event in enumerate(events) if type(event) is Wheels and keep[i]]
    t = times[rows]
    ticks = np.array([event.ticks for i in rows if type(event := events[i]) is Wheels], dtype=np.float64)
    return WheelSamples(rows, ticks.reshape(-1, 4), t, np.maximum(np.diff(t), MIN_STEP_S))


def _check_wheels(wheels: WheelSamples, counts_per_rev: int, bad: dict[int, str]) -> None:
    """Wheel samples whose counts jump, from the previous good sample, faster than MAX_WHEEL_RAD_S."""
    rows, ticks, t, dt = wheels
    if len(rows) < 2:
        return
    per_s = MAX_WHEEL_RAD_S / (2.0 * math.pi) * counts_per_rev
    steps = np.abs(np.diff(ticks, axis=0)).max(axis=1)
    jumps = steps > per_s * dt
    if not jumps.any():
        return  # every sample against the one before it: the usual case
    last = 0
    if jumps[0] and (len(jumps) == 1 or not jumps[1]):  # the first sample is the glitch: the next two agree
        bad[int(rows[0])] = _jump(ticks[0] - ticks[1], t[1] - t[0])
        last = 1
    for row in range(last + 1, len(rows)):  # a glitch is skipped: the next sample is compared with the last good one
        moved = ticks[row] - ticks[last]
        span = t[row] - t[last]
        if np.abs(moved).max() > per_s * max(span, MIN_STEP_S):
            bad[int(rows[row])] = _jump(moved, span)
        else:
            last = row


def _jump(moved: npt.NDArray[np.float64], dt: float) -> str:
    """The problem of a wheel sample that moved `moved` counts in `dt` seconds."""
    wheel = int(np.argmax(np.abs(moved)))
    return (
        f"{WHEEL_NAMES[wheel]} counts jump by {moved[wheel]:.3g} in {dt:.3g} s: faster than {MAX_WHEEL_RAD_S:.0e} "
        "rad/s, which no wheel turns"
    )


__all__ = ["MAX_TIME_S", "MAX_WHEEL_RAD_S", "Checked", "LogRefusedError", "check"]
