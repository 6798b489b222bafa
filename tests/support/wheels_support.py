"""Helpers for the wheel I/O tests: quadrature sequences and waiting on conditions without fixed sleeps."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from drivers.virtual.quadrature_signal import GRAY_CYCLE


def wait_until(condition: Callable[[], bool], timeout_s: float = 3.0) -> None:
    """Poll until `condition()` holds; fail the test after `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError("condition not reached in time")
        time.sleep(0.005)


def levels_of_positions(positions: list[int], a: int, b: int) -> npt.NDArray[np.uint32]:
    """Bank-1 words of an encoder on pins a, b walking through x4 positions, written out by hand from the
    Gray cycle (independent of drivers.virtual.quadrature_signal's vectorised version)."""
    words = []
    for position in positions:
        state = int(GRAY_CYCLE[position % 4])
        words.append(((state >> 1) << a) | ((state & 1) << b))
    return np.array(words, dtype=np.uint32)


def walk(start: int, moves: list[int]) -> list[int]:
    """Positions visited from `start` by steps of +1 / -1, one per edge (the start itself excluded)."""
    positions, position = [], start
    for move in moves:
        position += move
        positions.append(position)
    return positions
