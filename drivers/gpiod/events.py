"""Raw libgpiod v2 edge events to quadrature counts, a batch at a time (sans-I/O: bytes in, counts out; numpy).

Theory of operation: the kernel hands a line request's edge events out as `struct gpio_v2_line_event` records of 48
bytes: u64 timestamp_ns (CLOCK_MONOTONIC, taken in the hard IRQ), u32 id (1 rising, 2 falling), u32 offset (the
line; on the RP1 the BCM GPIO number), u32 seqno (request-wide, from 1), u32 line_seqno, u32 padding[6]. A batch of
bytes is viewed as a structured array, no copy and no Python object per edge. Each event sets its line to the level
its type reports while every other line keeps its latest level, which gives one level word per event: the same input
drivers.wheels.quadrature's decoder takes from pigpiod's reports, so both back-ends count with one table.

Levels come from the event types rather than from toggling: after a dropped event a toggled line would stay
inverted for good, where the next event's type puts it right. The kernel drops the oldest event when its buffer is
full and the gap shows in `seqno`: each missing number is one lost edge, counted and reported; drivers.gpiod.gaps
repairs the levels around the gap so that a single lost edge costs no count.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from drivers.gpiod.gaps import GapRepair, SeqnoGaps, gap_positions
from drivers.wheels.quadrature import Decoding, EncoderWiring, QuadratureDecoder

EVENT = np.dtype(
    [
        ("timestamp_ns", "=u8"),
        ("id", "=u4"),
        ("offset", "=u4"),
        ("seqno", "=u4"),
        ("line_seqno", "=u4"),
        ("padding", "=u4", (6,)),
    ]
)
"""`struct gpio_v2_line_event` (linux/gpio.h), in the machine's byte order as the kernel writes it."""
EVENT_SIZE = EVENT.itemsize
RISING_EDGE = 1
"""GPIO_V2_LINE_EVENT_RISING_EDGE"""
FALLING_EDGE = 2
"""GPIO_V2_LINE_EVENT_FALLING_EDGE"""

U32 = npt.NDArray[np.uint32]

assert EVENT_SIZE == 48, "struct gpio_v2_line_event is 48 bytes"


def decode_events(data: bytes | bytearray | memoryview) -> npt.NDArray[np.void]:
    """The whole records in `data` as a structured array of EVENT (a view, no copy)."""
    whole = len(data) - len(data) % EVENT_SIZE
    return np.frombuffer(data, dtype=EVENT, count=whole // EVENT_SIZE)


def encode_events(
    timestamps_ns: npt.ArrayLike,
    ids: npt.ArrayLike,
    offsets: npt.ArrayLike,
    seqnos: npt.ArrayLike,
    line_seqnos: npt.ArrayLike,
) -> bytes:
    """Records as the kernel writes them (padding zero), for stand-ins and benchmarks."""
    ids_array = np.asarray(ids)
    events = np.zeros(len(ids_array), dtype=EVENT)
    events["timestamp_ns"] = timestamps_ns
    events["id"] = ids_array
    events["offset"] = offsets
    events["seqno"] = seqnos
    events["line_seqno"] = line_seqnos
    return events.tobytes()


def levels_after_events(offsets: U32, rising: npt.NDArray[np.bool_], lines: Sequence[int], initial: int) -> U32:
    """The level word of `lines` after each event, starting from `initial`; bits of other lines stay as in `initial`.

    Each line reads the level its latest event reported. When every event changes its line (nothing lost, no type
    misread) that is a running XOR of one bit per event, one numpy pass; otherwise one pass per line: the index of
    the line's latest event, carried forward by a running maximum, picks the level it reported.
    """
    count = len(offsets)
    line_mask = sum(1 << line for line in lines)
    if np.all(offsets < 32) and np.all((np.uint32(line_mask) >> offsets) & np.uint32(1)):
        toggled = np.bitwise_xor.accumulate(np.left_shift(np.uint32(1), offsets)) ^ np.uint32(initial & 0xFFFFFFFF)
        if np.array_equal((toggled >> offsets) & np.uint32(1), rising):
            return toggled
    words = np.full(count, initial & ~line_mask & 0xFFFFFFFF, dtype=np.uint32)
    index = np.arange(count)
    for line in lines:
        latest = np.maximum.accumulate(np.where(offsets == line, index, -1))
        level = np.where(latest >= 0, rising[latest], bool((initial >> line) & 1))
        words |= level.astype(np.uint32) << np.uint32(line)
    return words


class EdgeEventDecoder:
    """Cumulative counts of several encoders from a byte stream of edge events (see the module docstring).

    Event times are kept on the quadrature decoder's integer time line as microseconds since `origin_ns` (a
    CLOCK_MONOTONIC time), so drivers.wheels.quadrature's edge-timed speed works unchanged.
    """

    def __init__(
        self, encoders: Sequence[EncoderWiring], decoding: Decoding, initial_levels: int, origin_ns: int
    ) -> None:
        self._lines = sorted({line for e in encoders for line in (e.a, e.b)})
        if self._lines[-1] > 31 or self._lines[0] < 0:
            raise ValueError(f"encoder lines must be GPIO 0-31, got {self._lines}")
        self.quadrature = QuadratureDecoder(encoders, decoding, initial_levels)
        self._levels = initial_levels
        self._origin_ns = origin_ns
        self._partial = b""
        self._gaps = SeqnoGaps()
        self._repair = GapRepair(self._lines)
        self._held = False
        self.events = 0
        """Events decoded since start."""

    @property
    def lost(self) -> int:
        """Events the kernel dropped since start (sequence-number gaps)."""
        return self._gaps.lost

    @property
    def levels(self) -> int:
        """The encoder lines' levels after the last event decoded, as a word (bit n = line n)."""
        return self._levels

    def restart(self, levels: int, origin_ns: int) -> None:
        """Start a new request: `levels` read now, events numbered from 1, times from `origin_ns`; counts carry on."""
        self.quadrature.restart(levels)
        self._levels = levels
        self._origin_ns = origin_ns
        self._partial = b""
        self._held = False
        self._gaps.restart()
        self._repair.restart()

    @property
    def holding(self) -> bool:
        """True while a batch is held back for a repair (see `feed`)."""
        return self._held

    def feed(self, data: bytes) -> int:
        """Decode the whole records of `data` after any earlier remainder; returns the events lost.

        A record split across calls waits for its end. A batch that leaves a line behind a gap with no later event
        to repair it (drivers.gpiod.gaps) is held back once: the next call or `flush()` decodes it with what follows.
        """
        if self._partial:
            data = self._partial + data
        events = decode_events(data)
        if not len(events):
            self._partial = data
            return 0
        seqnos, offsets, line_seqnos = events["seqno"], events["offset"], events["line_seqno"]
        rising = events["id"] == RISING_EDGE
        words = levels_after_events(offsets, rising, self._lines, self._levels)
        ticks_us = (events["timestamp_ns"].astype(np.int64) - self._origin_ns) // 1000
        stale = 0
        lossless = not self._gaps.missing(seqnos)
        if not lossless or self._repair.stale:
            gaps = gap_positions(seqnos, self._gaps.expected)
            words, stale = self._repair.repair(words, offsets, rising, line_seqnos, gaps)
            if stale and len(gaps) and not self._held:
                self._partial, self._held = data, True
                return 0
            # Just before an event its own line was at the opposite level: stepping through that state first counts
            # what was lost in the gap apart from the event's own edge (else two channels would seem to move at
            # once). A line still behind a previous batch's gap takes its step at this batch's first event.
            steps = np.union1d(gaps, [0]).astype(np.intp) if self._repair.stale else gaps
            own = offsets[steps]
            before = (words[steps] & ~(np.uint32(1) << own)) | ((~rising[steps]).astype(np.uint32) << own)
            self._levels = int(words[-1])
            words = np.insert(words, steps, before)
            ticks_us = np.insert(ticks_us, steps, ticks_us[steps])
        else:
            self._levels = int(words[-1])
        self._partial, self._held = data[len(events) * EVENT_SIZE :], False
        self._repair.commit(offsets, line_seqnos, stale, lossless=lossless)
        self.events += len(events)
        lost = self._gaps.check(seqnos)
        self.quadrature.decode(ticks_us, words)
        return lost

    def flush(self) -> int:
        """Decode a batch held back for a repair that has not come; returns the events lost."""
        return self.feed(b"") if self._held else 0

    def to_ticks_us(self, timestamp_ns: int) -> int:
        """A CLOCK_MONOTONIC time on the decoder's time line."""
        return (timestamp_ns - self._origin_ns) // 1000
