"""Bookkeeping of a pigpio notification stream: lost reports from sequence numbers, 32-bit ticks unwrapped and
mapped onto the daemon's monotonic clock (numpy over whole batches, no I/O).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt


class SequenceGaps:
    """Counts reports missing from a stream whose 16-bit sequence numbers should rise by one each report."""

    def __init__(self, first_seq: int | None = 0) -> None:
        # pigpiod numbers a handle's reports from 0; None takes whatever comes first (a stream joined midway).
        self._next: int | None = first_seq
        self.lost = 0

    def check(self, seq: npt.NDArray[np.uint16]) -> int:
        """Account for a batch of sequence numbers; returns how many reports are missing in or before it."""
        if not len(seq):
            return 0
        first = int(seq[0]) if self._next is None else self._next
        # Each gap of k reports adds k to the last number: the gaps of the whole batch telescope to one subtraction.
        # Losses are counted modulo 2^16: 65536 reports lost between two reads would go unseen.
        missing = (int(seq[-1]) - first - (len(seq) - 1)) & 0xFFFF
        self._next = (int(seq[-1]) + 1) & 0xFFFF
        self.lost += missing
        return missing

    def restart(self) -> None:
        """A new handle starts its own sequence at 0."""
        self._next = 0


class TickClock:
    """Unwraps pigpio's 32-bit microsecond ticks and maps them onto the monotonic clock.

    The map is anchored on a (tick, monotonic time) pair measured by asking pigpiod for its tick; `anchor()` may be
    called again to follow drift between the two clocks.
    """

    def __init__(self, tick: int, monotonic_s: float) -> None:
        self._last_tick = tick & 0xFFFFFFFF
        self._last_unwrapped = 0
        self._anchor_unwrapped = 0
        self._anchor_s = monotonic_s

    def unwrap(self, ticks: npt.NDArray[np.uint32]) -> npt.NDArray[np.int64]:
        """Ticks on one unbounded time line (microseconds since the first anchor).

        Each tick is read as a signed 32-bit difference from the last tick unwrapped before it (the batch before, or
        an anchor), so wrap-arounds and small backward steps both come out right, as long as a batch's ticks are
        less than 35 minutes from it (the encoders re-anchor every few seconds).
        """
        if not len(ticks):
            return np.zeros(0, dtype=np.int64)
        # three whole-batch operations: the difference wraps in uint32, and read as int32 it is the signed step
        steps = np.subtract(ticks, np.uint32(self._last_tick), dtype=np.uint32).view(np.int32)
        unwrapped = steps.astype(np.int64)
        unwrapped += self._last_unwrapped
        self._last_tick = int(ticks[-1])
        self._last_unwrapped = int(unwrapped[-1])
        return unwrapped

    def unwrap_one(self, tick: int) -> int:
        """One tick on the unwrapped time line (advances the unwrapper like a report would)."""
        return int(self.unwrap(np.array([tick & 0xFFFFFFFF], dtype=np.uint32))[0])

    def anchor(self, tick: int, monotonic_s: float) -> None:
        """Re-anchor: `tick` was read at `monotonic_s`."""
        self._anchor_unwrapped = self.unwrap_one(tick)
        self._anchor_s = monotonic_s

    def to_monotonic(self, unwrapped_us: int) -> float:
        """The monotonic time of an unwrapped tick."""
        return self._anchor_s + (unwrapped_us - self._anchor_unwrapped) * 1e-6

    def to_unwrapped(self, monotonic_s: float) -> int:
        """The unwrapped tick of a monotonic time."""
        return self._anchor_unwrapped + round((monotonic_s - self._anchor_s) * 1e6)
