"""Quadrature encoder signals for the simulator: wheel positions in counts to A/B levels, wheels merged into one
stream of bank-1 words for `VirtualPigpiod.drive_levels` (numpy, no I/O).

A position p (in x4 counts, forward positive) has state GRAY_CYCLE[p mod 4], with state = (A << 1) | B, the same
convention as drivers.wheels.quadrature: forward, A leads B.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

GRAY_CYCLE = np.array([0, 2, 3, 1], dtype=np.uint32)


def position_of_state(state: int) -> int:
    """The position in 0..3 whose state is `state` (to start a signal from the pins' present levels)."""
    return [int(s) for s in GRAY_CYCLE].index(state)


def encoder_words(positions: npt.ArrayLike, a: int, b: int) -> npt.NDArray[np.uint32]:
    """Bank-1 words holding the A and B levels (on bits a and b, other bits 0) of each position."""
    state = GRAY_CYCLE[np.asarray(positions, dtype=np.int64) % 4]
    return (((state >> np.uint32(1)) & np.uint32(1)) << np.uint32(a)) | ((state & np.uint32(1)) << np.uint32(b))


def merge_streams(
    streams: Sequence[tuple[npt.NDArray[np.int64], npt.NDArray[np.uint32], int]], initial: int = 0
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.uint32]]:
    """Merge per-encoder (ticks, words, mask) streams, each on its own bits, into one (ticks, bank words) stream.

    Ticks are unwrapped integers; the result is sorted by tick (stable: equal ticks keep stream order) and each word
    holds every stream's latest levels, starting from `initial`.
    """
    times: list[npt.NDArray[np.int64]] = []
    toggles: list[npt.NDArray[np.uint32]] = []
    for ticks, words, mask in streams:
        if not len(ticks):
            continue
        own = np.asarray(words, dtype=np.uint32) & np.uint32(mask)
        start = np.array([initial & mask], dtype=np.uint32)
        toggles.append(own ^ np.concatenate((start, own[:-1])))
        times.append(np.asarray(ticks, dtype=np.int64))
    if not times:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.uint32)
    when = np.concatenate(times)
    toggle = np.concatenate(toggles)
    order = np.argsort(when, kind="stable")
    return when[order], np.uint32(initial) ^ np.bitwise_xor.accumulate(toggle[order])
