"""Quadrature decoding over whole batches of bank-1 level words, and wheel speed from edge timing (numpy, no I/O).

Theory of operation: an encoder's state is s = (A << 1) | B. Turning forward (A leads B) walks the Gray cycle

        0 (A0 B0) --> 2 (A1 B0) --> 3 (A1 B1) --> 1 (A0 B1) --> 0 ...

and backward walks it the other way. A transition (previous state, state) is looked up in a 4x4 table: +1, -1, 0
(no change) or illegal (both channels changed at once: a step was missed, counted, never guessed). x4 counts every
edge; x2 only the edges of A; x1 only A's edge between states 0 and 2, +1 forward and -1 backward, so the count is
always the position in whole pulses whatever the reversals. A batch of N reports becomes a (wheels, N) array of
states and one table lookup: no Python per edge.

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


class QuadratureDecoder:
    """Cumulative counts of several encoders from a stream of bank-1 level words, decoded a batch at a time."""

    def __init__(self, encoders: Sequence[EncoderWiring], decoding: Decoding, initial_levels: int) -> None:
        self._table = transition_table(decoding)
        self._a = np.array([e.a for e in encoders], dtype=np.uint32)[:, None]
        self._b = np.array([e.b for e in encoders], dtype=np.uint32)[:, None]
        self._sign = np.array([e.sign for e in encoders], dtype=np.int64)
        self._state = self._states(np.array([initial_levels], dtype=np.uint32))[:, 0]
        wheels = len(encoders)
        self.counts = np.zeros(wheels, dtype=np.int64)
        """Cumulative counts per encoder, forward positive."""
        self.illegal = np.zeros(wheels, dtype=np.int64)
        """Illegal transitions per encoder (both channels changed between two reports)."""
        self.last_edge_us = np.full(wheels, -1, dtype=np.int64)
        """Tick of each encoder's last counted edge (-1: none yet)."""
        self._first_edge_us = np.full(wheels, -1, dtype=np.int64)
        self._first_edge_count = np.zeros(wheels, dtype=np.int64)

    def _states(self, levels: npt.NDArray[np.uint32]) -> npt.NDArray[np.uint8]:
        a = (levels[None, :] >> self._a) & np.uint32(1)
        b = (levels[None, :] >> self._b) & np.uint32(1)
        return ((a << np.uint32(1)) | b).astype(np.uint8)

    def restart(self, levels: int) -> None:
        """Start a new stream: take `levels` as the current state without counting and forget edge times."""
        self._state = self._states(np.array([levels], dtype=np.uint32))[:, 0]
        self.last_edge_us[:] = -1
        self._first_edge_us[:] = -1

    def decode(self, ticks_us: npt.NDArray[np.int64], levels: npt.NDArray[np.uint32]) -> None:
        """Decode level reports (bank 1 after each change) stamped with unwrapped ticks."""
        if not len(levels):
            return
        states = self._states(levels)
        previous = np.empty_like(states)
        previous[:, 0] = self._state
        previous[:, 1:] = states[:, :-1]
        self._state = states[:, -1].copy()
        self.illegal += np.count_nonzero((previous ^ states) == 3, axis=1)
        steps = np.take(self._table, (previous << np.uint8(2)) | states)
        moved = steps != 0
        edged = moved.any(axis=1)
        if not edged.any():
            return
        last = len(levels) - 1 - np.argmax(moved[:, ::-1], axis=1)
        fresh = edged & (self._first_edge_us < 0)
        if fresh.any():
            first = np.argmax(moved, axis=1)
            for wheel in np.flatnonzero(fresh):
                self._first_edge_us[wheel] = ticks_us[first[wheel]]
                self._first_edge_count[wheel] = self.counts[wheel] + self._sign[wheel] * steps[wheel, first[wheel]]
        self.last_edge_us[edged] = ticks_us[last[edged]]
        self.counts += self._sign * steps.sum(axis=1, dtype=np.int64)

    def take_first_edges(self) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
        """Tick and count of each encoder's first edge since the last call (tick -1: none), then forget them."""
        first = (self._first_edge_us.copy(), self._first_edge_count.copy())
        self._first_edge_us[:] = -1
        return first


class EdgeTimedSpeed:
    """Wheel speeds in counts per second from the decoder's edge times (see the module docstring)."""

    def __init__(self, wheels: int, stale_after_us: int) -> None:
        # plain lists: four wheels a publication, where numpy's per-element access cost more than the arithmetic
        self._reference_us = [-1] * wheels
        self._reference_count = [0] * wheels
        self._stale_after_us = stale_after_us
        self._speeds = [0.0] * wheels

    def update(self, decoder: QuadratureDecoder, now_us: int) -> npt.NDArray[np.float64]:
        """Speeds at `now_us` (a tick on the decoder's unwrapped time line), in counts per second."""
        first_edges = decoder.take_first_edges()
        first_us, first_count = first_edges[0].tolist(), first_edges[1].tolist()
        last_us, counts = decoder.last_edge_us.tolist(), decoder.counts.tolist()
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
        return np.array(speeds)
