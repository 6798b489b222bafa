"""PigpioEncoders reads the notification stream in batches paced to its publications, and sleeps at rest.

Each test runs the encoder source alone in an event loop whose selector counts the loop's passes (each pass is one
wake-up of the process), against the virtual pigpiod running in its own thread, fed edges by another thread in many
small flushes as pigpiod sends them. The bounds are generous functional ones: they count wake-ups, not time.
"""

from __future__ import annotations

import asyncio
import selectors
import threading
import time
from collections.abc import Callable, Coroutine
from typing import Any

from wheels_support import drive_wheels, eventually

from drivers.virtual.pigpiod import VirtualPigpiod
from drivers.wheels.encoders import IDLE_AFTER_QUIET, IDLE_KEEPALIVE_S, PigpioEncoders, WheelTicks
from robotd.config.model import EncodersConfig, PigpiodConfig


class CountingSelector(selectors.DefaultSelector):
    """The default selector, counting the loop's passes through `select`."""

    def __init__(self) -> None:
        super().__init__()
        self.passes = 0

    def select(self, timeout: float | None = None) -> list[tuple[selectors.SelectorKey, int]]:
        self.passes += 1
        return super().select(timeout)


def run_counted(main: Callable[[CountingSelector], Coroutine[Any, Any, None]]) -> None:
    """Run `main(selector)` in a fresh event loop on a counting selector."""
    selector = CountingSelector()
    with asyncio.Runner(loop_factory=lambda: asyncio.SelectorEventLoop(selector)) as runner:
        runner.run(main(selector))


def feed_in_flushes(
    server: VirtualPigpiod, encoders: EncodersConfig, flushes: int, spacing_s: float
) -> threading.Thread:
    """A thread that moves the front-left wheel 4 steps forward per flush, `flushes` times, `spacing_s` apart."""

    def feed() -> None:
        for _ in range(flushes):
            drive_wheels(server, encoders, [[1] * 4, [], [], []])
            time.sleep(spacing_s)

    feeder = threading.Thread(target=feed, name="edges")
    feeder.start()
    return feeder


def test_a_stream_of_small_flushes_is_read_in_paced_batches_with_every_count_and_loss() -> None:
    encoders = EncodersConfig()
    flushes, spacing_s = 200, 0.002  # pigpiod's flushes, about 400 ms of them
    published: list[WheelTicks] = []

    async def main(selector: CountingSelector) -> None:
        source = PigpioEncoders(encoders, PigpiodConfig(port=server.port))
        task = asyncio.create_task(source.run(published.append))
        try:
            await eventually(lambda: source.connected)
            server.lose_reports(3)  # lost in the middle of a batch: the sequence gap still shows
            passes, started = selector.passes, time.monotonic()
            feeder = feed_in_flushes(server, encoders, flushes, spacing_s)
            await asyncio.to_thread(feeder.join)  # one pass when it ends: this test does not poll meanwhile
            elapsed, passes = time.monotonic() - started, selector.passes - passes
            await eventually(lambda: source.counters.reports + 3 == 4 * flushes)
            await eventually(lambda: published[-1].ticks == source.ticks)
        finally:  # a failure leaves no connection open for a later test's garbage collection to report
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
        # At 50 publications a second the loop passes about 50 times a second, one per publication (polls included);
        # reading each flush as it arrives would pass once per flush, 500 times a second here.
        assert passes <= 2 * encoders.publish_rate_hz * elapsed + 10, (passes, elapsed)
        assert passes < flushes / 2
        assert source.counters.lost_reports == 3
        assert any(p.degraded for p in published)
        assert source.ticks[0] >= 4 * flushes - 4  # three edges lost, the rest counted, whatever the batching

    with VirtualPigpiod() as server:
        run_counted(main)


def test_at_rest_the_source_waits_for_an_edge_and_publishes_it_at_once() -> None:
    encoders = EncodersConfig()
    idle_s = 2.0
    published: list[WheelTicks] = []

    async def main(selector: CountingSelector) -> None:
        source = PigpioEncoders(encoders, PigpiodConfig(port=server.port))
        task = asyncio.create_task(source.run(published.append))
        try:
            await eventually(lambda: source.connected)
            await eventually(lambda: source.wakeups > IDLE_AFTER_QUIET)  # settled at rest
            passes, wakeups = selector.passes, source.wakeups
            await asyncio.sleep(idle_s)  # this test's own sleep: one pass
            passes, wakeups = selector.passes - passes, source.wakeups - wakeups
            # at rest only the keep-alive publishes (every IDLE_KEEPALIVE_S); at the publication rate it would be 100
            assert wakeups <= idle_s / IDLE_KEEPALIVE_S + 2, wakeups
            assert passes <= idle_s / IDLE_KEEPALIVE_S + 6, passes
            drive_wheels(server, encoders, [[1], [], [], []])
            await eventually(lambda: published[-1].ticks[0] == 1)  # an edge after a rest is read and published
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

    with VirtualPigpiod() as server:
        run_counted(main)
