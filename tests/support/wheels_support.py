"""Helpers for the wheel I/O tests: quadrature sequences and waiting on conditions without fixed sleeps."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from drivers.virtual.pigpiod import VirtualPigpiod
from drivers.virtual.quadrature_signal import GRAY_CYCLE, encoder_words, merge_streams, position_of_state
from drivers.wheels.encoders import wiring
from robotd.config.model import EncodersConfig


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


def drive_wheels(
    server: VirtualPigpiod,
    encoders: EncodersConfig,
    moves: list[list[int]],
    spacing_us: int = 20,
    start: int | None = None,
) -> np.ndarray:
    """Drive each wheel through its +1/-1 edge moves, starting from the pins' present state, interleaved in time, from
    tick `start` (default: a millisecond from now)."""
    streams, mask, levels = [], 0, 0
    start = server.tick() + 1000 if start is None else start
    for index, encoder in enumerate(wiring(encoders)):
        a, b = server.level(encoder.a), server.level(encoder.b)
        levels |= a << encoder.a | b << encoder.b
        positions = walk(position_of_state(a << 1 | b), moves[index])
        ticks = start + np.arange(len(positions), dtype=np.int64) * spacing_us * 4 + index * spacing_us
        bits = (1 << encoder.a) | (1 << encoder.b)
        streams.append((ticks, encoder_words(positions, encoder.a, encoder.b), bits))
        mask |= bits
    ticks, words = merge_streams(streams, levels)
    driven = (ticks & 0xFFFFFFFF).astype(np.uint32)
    server.drive_levels(driven, words, mask)
    return driven


async def eventually(
    condition: Callable[[], bool], timeout_s: float = 15.0, state: Callable[[], object] | None = None
) -> None:
    """Wait until `condition` holds, at most timeout_s: a bound on how long a real failure takes to show, not a
    speed target (the virtual pigpiod's thread lagged past 3 s in a full suite with a CPU hog beside it). On a
    timeout, the failure shows `state()`: whether the wait was slow or the condition can no longer hold."""
    try:
        async with asyncio.timeout(timeout_s):
            while not condition():
                await asyncio.sleep(0.005)
    except TimeoutError:
        shown = "" if state is None else f": {state()!r}"
        raise AssertionError(f"not reached within {timeout_s:g} s{shown}") from None
