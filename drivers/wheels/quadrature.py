"""Quadrature decoding over whole batches of bank-1 level words, and wheel speed from edge timing (numpy, no I/O).

Theory of operation: an encoder's state is s = (A << 1) | B. Turning forward (A leads B) walks the Gray cycle

        0 (A0 B0) --> 2 (A1 B0) --> 3 (A1 B1) --> 1 (A0 B1) --> 0 ...

and backward walks it the other way. A transition (previous state, state) is looked up in a 4x4 table: +1, -1, 0
(no change) or illegal (both channels changed at once: a step was missed, counted, never guessed). x4 counts every
edge; x2 only the edges of A; x1 only A's edge between states 0 and 2, +1 forward and -1 backward, so the count is
always the position in whole pulses whatever the reversals. Four wheels' states make one 8-bit joint state, so a
batch of N reports becomes N joint states and one lookup of (previous, current) in a table made from that 4x4 one:
no Python per edge, and a handful of whole-batch operations per batch (GROUP_WHEELS).

Speed comes from edge times, not from counts per window: the counts between the first and the last edge seen since
the previous estimate, over the time between those edges. At low speed that is a period measurement, exact to the
tick; when no edge arrives the speed is bounded by one count over the time since the last edge, so it decays to
zero instead of freezing at its last value.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt

ILLEGAL = 9  # table marker; never a count

#                     to state:   0        1        2        3         from state
_X4 = np.array([
                                  0,      -1,      +1,  ILLEGAL,    # 0  (A0 B0)
                                 +1,       0,  ILLEGAL,      -1,    # 1  (A0 B1)
                                 -1,  ILLEGAL,       0,      +1,    # 2  (A1 B0)
                            ILLEGAL,      +1,      -1,       0,     # 3  (A1 B1)
], dtype=np.int8)  # fmt: skip

# x2 keeps the transitions where only A changes (0<->2 and 1<->3); x1 keeps only 0<->2.
_A_EDGES = np.array([0, 0, 1, 0, 0, 0, 0, 1, 1, 0, 0, 0, 0, 1, 0, 0], dtype=bool)
_X1_EDGES = np.array([0, 0, 1, 0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 0, 0, 0], dtype=bool)

Decoding = Literal["x1", "x2", "x4"]


def transition_table(decoding: Decoding) -> npt.NDArray[np.int8]:
    """Count per transition, indexed by previous_state * 4 + state (illegal transitions count 0)."""
    counts = np.where(_X4 == ILLEGAL, 0, _X4).astype(np.int8)
    if decoding == "x2":
        counts[~_A_EDGES] = 0
    elif decoding == "x1":
        counts[~_X1_EDGES] = 0
    elif decoding != "x4":
        raise ValueError(f"decoding must be x1, x2 or x4, got {decoding!r}")
    return counts


@dataclass(frozen=True, slots=True)
class EncoderWiring:
    """One encoder: its two GPIOs and the sign that makes forward positive."""

    a: int
    b: int
    sign: int = 1


# Four wheels' states (8 bits) before and after a report index one 65536-entry table: a batch of reports is then a
# few operations on 1-D arrays, each costing microseconds of fixed overhead whatever its length, where one array of
# states per wheel took about twice as many (robotd bench encoders). More wheels are decoded four at a time.
GROUP_WHEELS = 4
_WHEEL_INDEX = np.arange(GROUP_WHEELS)
_FIELD_BITS = 16  # a wheel's field in a packed entry: its count + 1, so that a batch's sum never borrows
_FIELD_MASK = (1 << _FIELD_BITS) - 1
_MAX_BATCH = (1 << _FIELD_BITS) // 2 - 1  # reports whose field sums stay below 2**16


class _WheelGroup:
    """Up to four encoders decoded together: their joint state per level word from two tables (one per 16-bit half
    of the word), and per (previous, current) joint state the counts packed in one integer and a byte of flags
    (bits 0-3: the wheel counted an edge; bits 4-7: its transition was illegal)."""

    def __init__(self, encoders: Sequence[EncoderWiring], counts: npt.NDArray[np.int8]) -> None:
        self.wheels = len(encoders)
        half = np.arange(1 << 16)
        self.halves: list[tuple[int, npt.NDArray[np.intp]]] = []
        for which in (0, 1):
            table = np.zeros(1 << 16, dtype=np.intp)
            for index, encoder in enumerate(encoders):
                for gpio, weight in ((encoder.a, 2), (encoder.b, 1)):
                    if gpio // 16 == which:
                        table |= ((half >> (gpio % 16)) & 1) * (weight << 2 * index)
            if table.any():
                self.halves.append((which, table))
        joint = np.arange(1 << 16)
        previous, current = joint >> 8, joint & 255
        self.steps = np.zeros(1 << 16, dtype=np.int64)
        self.flags = np.zeros(1 << 16, dtype=np.uint8)
        for index, encoder in enumerate(encoders):
            transition = ((previous >> 2 * index) & 3) * 4 + ((current >> 2 * index) & 3)
            step = counts[transition].astype(np.int64) * encoder.sign
            self.steps |= (step + 1) << (_FIELD_BITS * index)
            self.flags |= ((step != 0) << index).astype(np.uint8)
            self.flags |= ((_X4[transition] == ILLEGAL) << (4 + index)).astype(np.uint8)
        self.state = 0

    def codes(self, halves: npt.NDArray[np.uint16], out: npt.NDArray[np.intp]) -> None:
        """The joint states of level words given as their (n, 2) 16-bit halves, into `out`."""
        (which, table), *rest = self.halves  # every encoder has a channel in one half or the other
        np.take(table, halves[:, which], out=out)
        for which, table in rest:
            out |= np.take(table, halves[:, which])


class QuadratureDecoder:
    """Cumulative counts of several encoders from a stream of bank-1 level words, decoded a batch at a time."""

    def __init__(self, encoders: Sequence[EncoderWiring], decoding: Decoding, initial_levels: int) -> None:
        counts = transition_table(decoding)
        self._groups = [
            _WheelGroup(encoders[first : first + GROUP_WHEELS], counts)
            for first in range(0, len(encoders), GROUP_WHEELS)
        ]
        self._take_states(initial_levels)
        wheels = len(encoders)
        # plain lists: a few wheels a batch, where numpy's per-element access cost more than the arithmetic
        self.counts = [0] * wheels
        """Cumulative counts per encoder, forward positive."""
        self.illegal = [0] * wheels
        """Illegal transitions per encoder (both channels changed between two reports)."""
        self.last_edge_us = [-1] * wheels
        """Tick of each encoder's last counted edge (-1: none yet)."""
        self._first_edge_us = [-1] * wheels
        self._first_edge_count = [0] * wheels

    def _take_states(self, levels: int) -> None:
        halves = np.array([levels & 0xFFFFFFFF], dtype="<u4").view("<u2").reshape(1, 2)
        code = np.zeros(1, dtype=np.intp)
        for group in self._groups:
            group.codes(halves, code)
            group.state = int(code[0])

    def restart(self, levels: int) -> None:
        """Start a new stream: take `levels` as the current state without counting and forget edge times."""
        self._take_states(levels)
        wheels = len(self.counts)
        self.last_edge_us = [-1] * wheels
        self._first_edge_us = [-1] * wheels

    def decode(self, ticks_us: npt.NDArray[np.int64], levels: npt.NDArray[np.uint32]) -> int:
        """Decode level reports (bank 1 after each change) stamped with unwrapped ticks; returns how many of the
        transitions were illegal."""
        illegal = 0
        for start in range(0, len(levels), _MAX_BATCH):
            batch = np.ascontiguousarray(levels[start : start + _MAX_BATCH], dtype="<u4")
            halves = batch.view("<u2").reshape(-1, 2)  # little-endian on any host: the low half first
            ticks = ticks_us[start : start + _MAX_BATCH]
            first_wheel = 0
            for group in self._groups:
                illegal += self._decode_group(group, first_wheel, ticks, halves)
                first_wheel += group.wheels
        return illegal

    def _decode_group(
        self, group: _WheelGroup, first_wheel: int, ticks_us: npt.NDArray[np.int64], halves: npt.NDArray[np.uint16]
    ) -> int:
        n, wheels = len(halves), group.wheels
        codes = np.empty(n + 1, dtype=np.intp)
        codes[0] = group.state
        group.codes(halves, codes[1:])
        group.state = int(codes[n])
        transitions = codes[:-1] << 8
        transitions |= codes[1:]
        flags = np.take(group.flags, transitions)
        illegal = 0
        if flags.max() >= 16:  # rare: a step missed
            found = np.unpackbits(flags[:, None], axis=1, bitorder="little")[:, 4 : 4 + wheels].sum(axis=0).tolist()
            for index, count in enumerate(found):
                self.illegal[first_wheel + index] += count
            illegal = sum(found)
        moved = np.unpackbits(flags[:, None], axis=1, count=wheels, bitorder="little")  # (n, wheels)
        first = moved.argmax(axis=0)  # each wheel's first counted edge (0 when it has none)
        last = n - 1 - moved[::-1].argmax(axis=0)
        edged = moved[first, _WHEEL_INDEX[:wheels]].tolist()
        if not any(edged):
            return illegal
        packed = np.take(group.steps, transitions)
        total = int(packed.sum())
        at_first = packed[first].tolist()
        edge_ticks = ticks_us[np.concatenate((first, last))].tolist()
        counts, last_edge_us = self.counts, self.last_edge_us
        first_edge_us, first_edge_count = self._first_edge_us, self._first_edge_count
        for index, has_edge in enumerate(edged):
            if not has_edge:
                continue
            wheel, shift = first_wheel + index, _FIELD_BITS * index
            before = counts[wheel]
            counts[wheel] = before + ((total >> shift) & _FIELD_MASK) - n
            last_edge_us[wheel] = edge_ticks[wheels + index]
            if first_edge_us[wheel] < 0:
                first_edge_us[wheel] = edge_ticks[index]
                first_edge_count[wheel] = before + ((at_first[index] >> shift) & _FIELD_MASK) - 1
        return illegal

    def take_first_edges(self) -> tuple[list[int], list[int]]:
        """Tick and count of each encoder's first edge since the last call (tick -1: none), then forget them."""
        first = (self._first_edge_us, self._first_edge_count.copy())
        self._first_edge_us = [-1] * len(first[0])
        return first


class EdgeTimedSpeed:
    """Wheel speeds in counts per second from the decoder's edge times (see the module docstring)."""

    def __init__(self, wheels: int, stale_after_us: int) -> None:
        # plain lists: four wheels a publication, where numpy's per-element access cost more than the arithmetic
        self._reference_us = [-1] * wheels
        self._reference_count = [0] * wheels
        self._stale_after_us = stale_after_us
        self._speeds = [0.0] * wheels

    def update(self, decoder: QuadratureDecoder, now_us: int) -> list[float]:
        """Speeds at `now_us` (a tick on the decoder's unwrapped time line), in counts per second."""
        first_us, first_count = decoder.take_first_edges()
        last_us, counts = decoder.last_edge_us, decoder.counts
        speeds, references_us, references_count = self._speeds, self._reference_us, self._reference_count
        for wheel, (first, last) in enumerate(zip(first_us, last_us, strict=True)):
            if first >= 0:
                reference_us, reference_count = references_us[wheel], references_count[wheel]
                # After a standstill the old reference would average the pause in: measure within this window.
                if reference_us < 0 or first - reference_us > self._stale_after_us:
                    reference_us, reference_count = first, first_count[wheel]
                span_us = last - reference_us
                if span_us > 0:
                    speeds[wheel] = (counts[wheel] - reference_count) * 1e6 / span_us
                references_us[wheel], references_count[wheel] = last, counts[wheel]
            elif last >= 0:
                bound = 1e6 / max(now_us - last, 1)
                speeds[wheel] = min(max(speeds[wheel], -bound), bound)
        return list(speeds)
