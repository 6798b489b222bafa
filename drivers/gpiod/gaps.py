"""Events the kernel dropped: counted from sequence-number gaps, and the encoder levels repaired around them (numpy).

A request numbers its events from 1 (`seqno`) and each line's events from 1 (`line_seqno`). When the kernel's
buffer overflows it drops the oldest event; the next event read then follows a gap (its `seqno` is not the previous
one's plus one) and, on the lines that lost events, their next event follows a `line_seqno` gap.

Why repair: a line that lost an edge would keep reading its old level until its next event, and the other channel's
edges of that encoder would then be decoded against a wrong level, as steps in the wrong direction. But an edge
always changes its line's level, so just before a line's next event the line was at the opposite of the level that
event reports. `GapRepair` gives a line that lost edges (its next event's `line_seqno` jumped) that level from the
latest gap before that event on: one dropped edge then costs no count. Exact when each line that lost an edge has
an event of its own before the next gap (the loss is placed at the latest gap when several lie before that event); a
line whose next event is in a later read is reported stale so the decoder can wait for it once. Two or more edges
lost in a row on one encoder can still alias (a quadrature step is known only modulo 4): losses are always counted
and reported, never hidden.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

FIRST_SEQNO = 1
"""A request numbers its events, and each line's events, from 1."""

U32 = npt.NDArray[np.uint32]


class SeqnoGaps:
    """Counts events missing from a request whose 32-bit sequence numbers should rise by one each event."""

    def __init__(self) -> None:
        self._next = FIRST_SEQNO
        self.lost = 0

    @property
    def expected(self) -> int:
        """The sequence number the next event should carry."""
        return self._next

    def missing(self, seqnos: U32) -> int:
        """How many events are missing in or before a batch of sequence numbers (nothing is recorded)."""
        if not len(seqnos):
            return 0
        # Each gap of k adds k to the last number: the gaps of a whole batch telescope to one subtraction.
        return (int(seqnos[-1]) - self._next - (len(seqnos) - 1)) & 0xFFFFFFFF

    def check(self, seqnos: U32) -> int:
        """Account for a batch of sequence numbers; returns how many events are missing in or before it."""
        missing = self.missing(seqnos)
        if len(seqnos):
            self._next = (int(seqnos[-1]) + 1) & 0xFFFFFFFF
            self.lost += missing
        return missing

    def restart(self) -> None:
        """A new request numbers its events from 1 again."""
        self._next = FIRST_SEQNO


def gap_positions(seqnos: U32, expected_first: int) -> npt.NDArray[np.intp]:
    """Positions of the events whose sequence number does not follow the one before (the first: `expected_first`)."""
    steps = np.empty(len(seqnos), dtype=np.uint32)
    steps[0] = (int(seqnos[0]) - expected_first + 1) & 0xFFFFFFFF
    steps[1:] = seqnos[1:] - seqnos[:-1]
    return np.flatnonzero(steps != 1)


class GapRepair:
    """Repairs the level words of a batch with gaps (see the module docstring); remembers each line's last seqno."""

    def __init__(self, lines: Sequence[int]) -> None:
        self._lines = list(lines)
        self._last_line_seqno = np.full(32, FIRST_SEQNO - 1, dtype=np.uint32)  # by line offset
        self.stale = 0
        """Lines (bits) behind a gap whose next event has not been read yet."""

    def restart(self) -> None:
        """A new request numbers each line's events from 1 again."""
        self._last_line_seqno[:] = FIRST_SEQNO - 1
        self.stale = 0

    def repair(
        self, words: U32, offsets: U32, rising: npt.NDArray[np.bool_], line_seqnos: U32, gaps: npt.NDArray[np.intp]
    ) -> tuple[U32, int]:
        """The batch's level words with the lines that lost edges repaired, and the lines left stale (bits).

        Nothing is recorded: `commit` does that once the batch is decoded.
        """
        count = len(offsets)
        index = np.arange(count)
        marks = np.full(count, -1)
        marks[gaps] = gaps
        last_gap = np.maximum.accumulate(marks)
        # The first gap after each position (count: none), to place a loss at the latest gap before the next event.
        next_gap = np.full(count, count)
        upcoming = np.minimum.accumulate(np.where(marks >= 0, index, count)[::-1])[::-1]
        next_gap[:-1] = upcoming[1:]
        repaired = words.copy()
        stale = 0
        for line in self._lines:
            on_line = offsets == line
            latest = np.maximum.accumulate(np.where(on_line, index, -1))
            since_gap = np.maximum(last_gap, 0) if (self.stale >> line) & 1 else last_gap
            behind = since_gap > latest
            if not behind.any():
                continue
            stale |= int(behind[-1]) << line
            events = np.flatnonzero(on_line)
            if not len(events):
                continue
            own = line_seqnos[events]
            previous = np.concatenate((self._last_line_seqno[line : line + 1], own[:-1]))
            jumped = np.zeros(count + 1, dtype=bool)
            jumped[events] = (own - previous) != 1  # this line lost events before this one
            after = np.minimum.accumulate(np.where(on_line, index, count)[::-1])[::-1]  # its next event, at or after
            fix = behind & jumped[after] & (next_gap > after)
            if fix.any():
                before = ~rising[np.minimum(after, count - 1)]
                bit = np.uint32(1 << line)
                repaired = np.where(fix, (repaired & ~bit) | (before.astype(np.uint32) << np.uint32(line)), repaired)
        return repaired, stale

    def commit(self, offsets: U32, line_seqnos: U32, stale: int, *, lossless: bool) -> None:
        """Record a decoded batch: each line's last sequence number and the lines left stale.

        A `lossless` batch (no gap) numbered every line's events one by one: counting them per line is enough.
        """
        if lossless:
            counts = np.bincount(offsets, minlength=32)[:32].astype(np.uint32)
            self._last_line_seqno += counts  # wraps at 2^32, as the kernel's numbers do
        else:
            for line in self._lines:
                events = np.flatnonzero(offsets == line)
                if len(events):
                    self._last_line_seqno[line] = line_seqnos[events[-1]]
        self.stale = stale
