"""Encoder counters that wrap, unwrapped in a decoded sensor log before it is checked and replayed.

Theory of operation. The format's wheel counts are cumulative, but a log written from a microcontroller's encoder
count often carries a 16-bit timer (or a 32-bit register) that wraps: at 6800 counts a turn a 16-bit counter wraps
every 9.6 turns of the wheel, under 3 m of a small robot's travel. Read as motion, each wrap throws the robot metres
in one sample (and robotd.logs.logcheck, whose bound is a corrupted count's, lets a 16-bit wrap through). A step is
taken for a wrap when it is beyond any wheel's speed (WRAP_WHEEL_RAD_S), within it once whole turns of a 16- or
32-bit counter are taken off, and the counts on both sides of it are in that counter's range (signed or unsigned);
every later count of that wheel then carries those turns. Any other step beyond a wheel's speed is left to the check
(a glitch, a corrupted count). Pure.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from robotd.logs.events import WHEEL_NAMES, Event, Wheels

FloatArray = npt.NDArray[np.float64]

WRAP_WHEEL_RAD_S = 200.0  # ~1900 rpm: beyond a small robot's wheel, and far below a 16-bit wrap between samples
COUNTER_BITS = (16, 32)


class WheelSamples(NamedTuple):
    """A log's wheel samples as arrays: their events' indices, counts (one row each, as floats), times, and the time
    from each to the next (at least the check's shortest step)."""

    rows: list[int]
    ticks: FloatArray
    t: FloatArray
    dt: FloatArray


def unwrap(
    events: list[Event], wheels: WheelSamples, counts_per_rev: int
) -> tuple[list[Event], WheelSamples, list[tuple[int, str]]]:
    """The events with every wrapped wheel counter unwrapped, and their samples (the same list and samples when none
    wrapped), and one note per wheel that wrapped: (the event of its first wrap, "front-left counts: a 16-bit counter,
    unwrapped 3 times from here")."""
    rows, ticks = wheels.rows, wheels.ticks
    if len(rows) < 2:
        return events, wheels, []
    limit = WRAP_WHEEL_RAD_S / (2.0 * math.pi) * counts_per_rev * wheels.dt
    # the floats only find the candidate steps (exact for counters up to 2^53); the wraps are judged on the integers
    beyond = np.abs(np.diff(ticks, axis=0)) > limit[:, None]
    if not beyond.any():
        return events, wheels, []  # the usual case
    samples = [event for i in rows if type(event := events[i]) is Wheels]
    added: dict[int, list[int]] = {}  # sample -> the counts to add to it and every later one, per wheel
    notes: list[tuple[int, str]] = []
    for wheel in range(4):
        wraps: list[tuple[int, int]] = []  # (sample, counter bits)
        for k in np.flatnonzero(beyond[:, wheel]).tolist():
            wrap = _wrap(samples[k].ticks[wheel], samples[k + 1].ticks[wheel], float(limit[k]))
            if wrap is not None:
                added.setdefault(k + 1, [0, 0, 0, 0])[wheel] += wrap[0]
                wraps.append((k + 1, wrap[1]))
        if wraps:
            first, bits = wraps[0]
            times = "once" if len(wraps) == 1 else f"{len(wraps)} times"
            notes.append(
                (rows[first], f"{WHEEL_NAMES[wheel]} counts: a {bits}-bit counter, unwrapped {times} from here")
            )
    if not added:
        return events, wheels, []
    events = list(events)
    carried = [0, 0, 0, 0]
    for k in range(min(added), len(samples)):
        if k in added:
            carried = [c + a for c, a in zip(carried, added[k], strict=True)]
        sample = samples[k]
        a, b, c, d = sample.ticks
        samples[k] = Wheels(sample.t, (a + carried[0], b + carried[1], c + carried[2], d + carried[3]))
        events[rows[k]] = samples[k]
    return events, wheels._replace(ticks=np.array([sample.ticks for sample in samples], dtype=np.float64)), notes


def _wrap(before: int, after: int, bound: float) -> tuple[int, int] | None:
    """(the counts to add, the counter's bits) when the step from `before` to `after`, beyond `bound`, is a 16- or
    32-bit counter's wrap; else None."""
    step = after - before
    for bits in COUNTER_BITS:
        if not (_in_range(before, bits) and _in_range(after, bits)):
            continue
        turn = 1 << bits
        turns = round(step / turn)
        if turns and abs(step - turns * turn) <= bound:
            return -turns * turn, bits
    return None


def _in_range(count: int, bits: int) -> bool:
    """Whether a count can be a `bits`-bit counter's, signed or unsigned."""
    return -(1 << (bits - 1)) <= count < (1 << bits)


__all__ = ["WRAP_WHEEL_RAD_S", "WheelSamples", "unwrap"]
