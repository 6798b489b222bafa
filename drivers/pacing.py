"""Periodic wake-ups on a shared grid of loop time, so tasks of the same rate wake together.

Theory of operation. Every wake-up of the event loop costs a context switch and a pass through asyncio's machinery,
whatever the loop then does. Two tasks at 50 Hz that each sleep their own period from their own start wake the
loop 100 times a second; scheduled at the multiples of their period on the loop's clock (`next_tick`) and woken at
exactly that time (`sleep_until`, one `call_at` rather than a `sleep` whose start drifts by the time the caller took),
they fall due in the same pass of the loop and wake it 50 times. A rate that divides another's (20 Hz and 100 Hz)
shares its wake-ups as well.

A thread that serves a queue for the loop (the sensor log's writer, the live view's publisher) wakes for a batch, not
for each item: `take_waiting` takes what came since it last woke, and `sleep_out` keeps it asleep for the rest of
BATCH_PERIOD_S. Woken for each of some 200 items a second, such a thread started each from cold caches and spent
several times the CPU of the same work done together.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import queue
import time
from typing import TypeVar

T = TypeVar("T")

BATCH_PERIOD_S = 0.04
"""How often at most a queue's thread wakes: below what a viewer's eye or a log's reader notices."""


def next_tick(now: float, period_s: float) -> float:
    """The first multiple of `period_s` after `now` (loop time)."""
    return (math.floor(now / period_s) + 1) * period_s


async def sleep_until(deadline: float, loop: asyncio.AbstractEventLoop | None = None) -> None:
    """Sleep until the loop's clock reaches `deadline` (at once when it has); `loop`: the running loop, when the
    caller holds it (Python 3.11 asks the kernel for the process id to find it: a system call per period saved)."""
    if loop is None:
        loop = asyncio.get_running_loop()
    if deadline <= loop.time():
        await asyncio.sleep(0)
        return
    woken: asyncio.Future[None] = loop.create_future()
    timer = loop.call_at(deadline, _wake, woken)
    try:
        await woken
    finally:
        timer.cancel()


def _wake(woken: asyncio.Future[None]) -> None:
    if not woken.done():
        woken.set_result(None)


def take_waiting(first: T, source: queue.Queue[T]) -> list[T]:
    """`first` and every item `source` holds now, in order."""
    items = [first]
    with contextlib.suppress(queue.Empty):
        while True:
            items.append(source.get_nowait())
    return items


def sleep_out(woke: float, period_s: float = BATCH_PERIOD_S) -> None:
    """Sleep this thread until `period_s` after `woke` (time.monotonic()); at once when that has passed."""
    time.sleep(max(0.0, woke + period_s - time.monotonic()))
