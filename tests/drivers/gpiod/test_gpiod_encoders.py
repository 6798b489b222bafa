"""GpiodEncoders reading real gpio_v2_line_event records from a pipe on the event loop (the virtual chip)."""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable

import pytest
from gpiod_support import drive_turns

from drivers.gpiod.encoders import GpiodEncoders, KernelClock
from drivers.gpiod.lines import EventLineSettings, GpioUnavailableError
from drivers.virtual.event_pipe import VirtualEventLines
from drivers.wheels.encoders import WheelTicks
from drivers.wheels.quadrature import EncoderWiring

WIRING = [EncoderWiring(5, 6), EncoderWiring(13, 19), EncoderWiring(26, 16), EncoderWiring(20, 21, -1)]
CPR = 6800


async def eventually(condition: Callable[[], bool], timeout_s: float = 5.0) -> None:
    async with asyncio.timeout(timeout_s):
        while not condition():
            await asyncio.sleep(0.005)


async def stop(task: asyncio.Task[None]) -> None:
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task


def source_on(chip: VirtualEventLines, **options: object) -> GpiodEncoders:
    return GpiodEncoders(WIRING, CPR, publish_rate_hz=100.0, open_lines=chip.open, **options)  # type: ignore[arg-type]


async def test_one_request_for_all_eight_lines_with_a_large_buffer_released_on_cancel() -> None:
    chip = VirtualEventLines()
    settings = EventLineSettings(pull="down", event_buffer_size=1024)
    source = source_on(chip, settings=settings)
    task = asyncio.create_task(source.run(lambda ticks: None))
    await eventually(lambda: source.connected)
    await stop(task)
    assert chip.requests == [([5, 6, 13, 16, 19, 20, 21, 26], settings)]
    chip.open([5, 6], settings).release()  # cancelling the source released its lines: they are free again


async def test_counts_of_the_virtual_robots_edges_through_the_pipe_are_exact() -> None:
    chip = VirtualEventLines()
    source = source_on(chip)
    published: list[WheelTicks] = []
    task = asyncio.create_task(source.run(published.append))
    await eventually(lambda: source.connected)
    turns = [1.25, -0.75, 0.1, 2.0]  # 27,880 edges, driven 5 ms at a time as the virtual robot drives them
    parts, start_ns, ends = 40, time.monotonic_ns(), [0, 0, 0, 0]
    for part in range(parts):
        before, after = [t * part / parts for t in turns], [t * (part + 1) / parts for t in turns]
        ends = drive_turns(chip, WIRING, after, start_ns + part * 5_000_000, 5_000_000, CPR, before)
        await asyncio.sleep(0.005)
    expected = [end * e.sign for end, e in zip(ends, WIRING, strict=True)]
    await eventually(lambda: list(source.ticks) == expected)
    await eventually(lambda: published[-1].ticks == tuple(expected))
    await stop(task)
    assert chip.events_dropped == 0
    assert source.counters.lost_reports == 0
    assert source.counters.reports == sum(abs(end) for end in ends) == 27_880
    assert not published[-1].degraded
    assert published[-1].speeds_rad_s[1] <= 0 <= published[-1].speeds_rad_s[0]


@pytest.mark.parametrize(("lost", "counted"), [(1, 68), (3, 64)])
async def test_lost_events_are_counted_and_mark_the_publication_degraded(lost: int, counted: int) -> None:
    chip = VirtualEventLines()
    source = source_on(chip)
    published: list[WheelTicks] = []
    task = asyncio.create_task(source.run(published.append))
    await eventually(lambda: len(published) >= 1)
    assert not published[-1].degraded
    chip.lose_events(lost)
    drive_turns(chip, WIRING, [0.01, 0, 0, 0], time.monotonic_ns(), 5_000_000, CPR)  # 68 edges of one wheel
    await eventually(lambda: source.counters.reports == 68 - lost)
    seen = len(published)
    await eventually(lambda: len(published) >= seen + 2)
    await stop(task)
    assert source.counters.lost_reports == lost
    assert any(p.degraded for p in published[seen - 1 :])
    assert not published[-1].degraded  # it marks the publication that covered the loss, then clears
    # One lost edge is repaired from the next events; three in a row on one encoder alias (three steps forward
    # read as one back): the count is off by 4, which the degraded publication owns up to.
    assert published[-1].ticks[0] == counted


async def test_a_failed_request_is_opened_again_and_counting_carries_on() -> None:
    chip = VirtualEventLines()
    source = source_on(chip, reopen_max_s=0.1)
    published: list[WheelTicks] = []
    task = asyncio.create_task(source.run(published.append))
    await eventually(lambda: source.connected)
    drive_turns(chip, WIRING, [0.001, 0, 0, 0], time.monotonic_ns(), 1_000_000, CPR)
    await eventually(lambda: source.ticks[0] == 6)
    chip.unplug()  # the request's fd reads end of file
    await eventually(lambda: source.counters.reconnects == 1)
    seen = len(published)
    ends = drive_turns(chip, WIRING, [0.002, 0, 0, 0], time.monotonic_ns(), 1_000_000, CPR, [0.001, 0, 0, 0])
    await eventually(lambda: source.ticks[0] == ends[0] == 13)
    await eventually(lambda: len(published) > seen)
    await stop(task)
    assert len(chip.requests) == 2
    assert any(p.degraded for p in published)


async def test_lines_that_cannot_be_requested_raise_a_clear_error_at_start() -> None:
    def busy(offsets: object, settings: object) -> VirtualEventLines:
        raise GpioUnavailableError("cannot request encoder lines [5, 6] on /dev/gpiochip0: another process holds them")

    source = GpiodEncoders(WIRING, CPR, open_lines=busy)  # type: ignore[arg-type]
    with pytest.raises(GpioUnavailableError, match="another process holds them"):
        await source.run(lambda ticks: None)


async def test_speeds_come_from_kernel_timestamps_mapped_onto_the_daemon_clock() -> None:
    chip = VirtualEventLines()
    kernel_at_open = 7_000_000_000_000
    now = [100.0]
    source = GpiodEncoders(
        WIRING,
        CPR,
        publish_rate_hz=1.0,
        open_lines=chip.open,
        clock=lambda: now[0],
        kernel_clock_ns=lambda: kernel_at_open,
    )
    task = asyncio.create_task(source.run(lambda ticks: None))
    await eventually(lambda: source.connected)
    # Wheel 0 turns at one revolution per second for 0.1 s, starting 0.2 s after the request opened.
    drive_turns(chip, WIRING, [0.1, 0, 0, 0], kernel_at_open + 200_000_000, 100_000_000, CPR)
    await eventually(lambda: chip.events_written == 680)
    await asyncio.sleep(0.02)  # the loop reads the pipe
    now[0] = 100.3001  # the daemon's clock, 0.1 ms after the last edge
    first = source.snapshot()
    now[0] = 100.4  # 100 ms later, no edge since: at most one count in that time
    later = source.snapshot()
    await stop(task)
    assert (first.t, first.ticks[0]) == (100.3001, 680)
    assert first.speeds_rad_s[0] == pytest.approx(2 * math.pi, rel=0.01)
    assert later.speeds_rad_s[0] == pytest.approx(10 * 2 * math.pi / CPR, rel=0.01)


def test_the_kernel_clock_maps_both_ways() -> None:
    mapping = KernelClock(5_000_000_000, 12.5)
    assert mapping.to_monotonic(5_250_000_000) == pytest.approx(12.75)
    assert mapping.to_kernel_ns(12.75) == 5_250_000_000
