"""PigpioEncoders over real loopback sockets against the virtual pigpiod; the per-edge baseline beside it."""

from __future__ import annotations

import asyncio
import socket
from dataclasses import replace

import pytest
from wheels_support import drive_wheels, eventually, wait_until

from drivers.pigpiod.client import PigpiodUnavailableError, PigpioLink
from drivers.pigpiod.protocol import Cmd, Mode, Pull
from drivers.virtual.pigpiod import VirtualPigpiod
from drivers.wheels.encoders import PigpioEncoders, WheelTicks, wiring
from drivers.wheels.quadrature import Decoding
from robotd.bench.encoders import CallbackEncoders
from robotd.config.model import EncodersConfig, PigpiodConfig

# The virtual pigpiod starts 5 s before pigpio's 32-bit tick wraps, and the test stamps its edges from 40 ms before the
# wrap: the stream crosses it however long a busy machine takes to connect (a start 30 ms before the wrap, with edges
# stamped at the present tick, missed it once the connection took longer than that).
NEAR_WRAP = (1 << 32) - 5_000_000
BEFORE_WRAP = (1 << 32) - 40_000


async def stop(task: asyncio.Task[None]) -> None:
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task


MOVES = [
    [1] * 400 + [-1] * 150 + [1] * 3,  # forward, back, forward again
    [-1] * 257,  # backward
    [1, -1] * 60 + [1] * 9,  # dithering then a few steps
    [1] * 1000,
]


@pytest.mark.parametrize("decoding", ["x1", "x2", "x4"])
async def test_counts_through_the_socket_are_exact_across_the_tick_wrap(decoding: Decoding) -> None:
    encoders = replace(EncodersConfig(), decoding=decoding)
    # The last wheel counts backward: its sign is -1.
    wheels = replace(encoders.wheels, rear_right=replace(encoders.wheels.rear_right, sign=-1))
    encoders = replace(encoders, wheels=wheels)
    async with VirtualPigpiod(start_tick=NEAR_WRAP) as server:
        source = PigpioEncoders(encoders, PigpiodConfig(port=server.port))
        published: list[WheelTicks] = []
        task = asyncio.create_task(source.run(published.append))
        try:
            await eventually(lambda: source.connected)
            assert server.tick() < BEFORE_WRAP, "the test took 5 s to connect: the stream would be stamped in the past"
            driven = drive_wheels(server, encoders, MOVES, start=BEFORE_WRAP)
            total_edges = sum(len(m) for m in MOVES)
            await eventually(
                lambda: source.counters.reports == total_edges, state=lambda: (total_edges, source.counters)
            )
            await eventually(lambda: len(published) >= 2)
        finally:  # a failure leaves no connection open for a later test's garbage collection to report
            await stop(task)
    assert driven[-1] < driven[0]  # the edges' ticks wrapped around 2^32
    # Every wheel starts at position 2 of the Gray cycle (pins pulled up).
    assert list(source.ticks) == [_count_from(2, m, decoding) * s for m, s in zip(MOVES, [1, 1, 1, -1], strict=True)]
    assert published[-1].ticks == source.ticks
    assert source.counters.lost_reports == 0
    assert source.counters.illegal_transitions == (0, 0, 0, 0)
    assert not published[-1].degraded


async def test_the_source_is_connected_only_once_pigpiod_reports_its_edges(monkeypatch: pytest.MonkeyPatch) -> None:
    # a busy machine held the notify-begin command back while the source already said it was connected: a test that
    # drove edges then saw none of them reported
    release = asyncio.Event()
    command = PigpioLink.command

    async def held_notify_begin(
        link: PigpioLink, cmd: int, p1: int = 0, p2: int = 0, *, extension: bytes = b"", unsigned: bool = False
    ) -> int:
        if cmd == Cmd.NB:
            await release.wait()
        return await command(link, cmd, p1, p2, extension=extension, unsigned=unsigned)

    monkeypatch.setattr(PigpioLink, "command", held_notify_begin)
    async with VirtualPigpiod() as server:
        source = PigpioEncoders(EncodersConfig(), PigpiodConfig(port=server.port))
        task = asyncio.create_task(source.run(lambda _: None))
        try:
            await eventually(lambda: len(server.notify_handles()) > 0)  # connecting: pins set, the handle open
            await asyncio.sleep(0.1)
            assert not source.connected
            assert list(server.notify_handles().values()) == [0]  # nothing monitored yet
            release.set()
            await eventually(lambda: source.connected)
            assert list(server.notify_handles().values()) != [0]
        finally:
            await stop(task)


def _count_from(start: int, moves: list[int], decoding: str) -> int:
    """Counts of the x1/x2/x4 edges crossed walking `moves` from Gray position `start` (A rises between 0 and 1,
    B rises between 1 and 2, A falls between 2 and 3, B falls between 3 and 4)."""
    counted = {"x4": {0, 1, 2, 3}, "x2": {0, 2}, "x1": {0}}[decoding]
    count, position = 0, start
    for move in moves:
        edge = position % 4 if move > 0 else (position - 1) % 4
        if edge in counted:
            count += move
        position += move
    return count


async def test_pins_are_configured_from_the_config() -> None:
    encoders = replace(EncodersConfig(), glitch_filter_us=7, pull="down")
    async with VirtualPigpiod() as server:
        source = PigpioEncoders(encoders, PigpiodConfig(port=server.port))
        task = asyncio.create_task(source.run(lambda ticks: None))
        await eventually(lambda: source.connected)
        for encoder in wiring(encoders):
            for gpio in (encoder.a, encoder.b):
                assert (server.mode(gpio), server.pull(gpio), server.glitch_filter_us(gpio)) == (
                    Mode.INPUT,
                    Pull.DOWN,
                    7,
                )
        assert list(server.notify_handles().values()) == [sum((1 << e.a) | (1 << e.b) for e in wiring(encoders))]
        await stop(task)


async def test_glitches_shorter_than_the_filter_are_not_counted() -> None:
    encoders = replace(EncodersConfig(), glitch_filter_us=5)
    async with VirtualPigpiod() as server:
        source = PigpioEncoders(encoders, PigpiodConfig(port=server.port))
        task = asyncio.create_task(source.run(lambda ticks: None))
        await eventually(lambda: source.connected)
        a = encoders.wheels.front_left.a
        start = server.tick() + 1000
        # 2 us spikes on channel A (noise on the cable), then one real edge that holds.
        spikes = [start + 50 * i + d for i in range(10) for d in (0, 2)]
        server.drive_edges(a, [*spikes, start + 1000], [0, 1] * 10 + [0])
        await eventually(lambda: source.counters.reports == 1)
        await stop(task)
    assert source.ticks[0] == 1  # A fell from the pulled-up state 3 to 1: one step forward, nothing else


async def test_lost_reports_are_counted_and_mark_the_odometry_degraded() -> None:
    encoders = EncodersConfig()
    async with VirtualPigpiod() as server:
        source = PigpioEncoders(encoders, PigpiodConfig(port=server.port))
        published: list[WheelTicks] = []
        task = asyncio.create_task(source.run(published.append))
        await eventually(lambda: source.connected)
        await eventually(lambda: len(published) >= 1)
        assert not published[-1].degraded
        server.lose_reports(3)
        drive_wheels(server, encoders, [[1] * 8, [], [], []])
        await eventually(lambda: source.counters.reports == 5)
        seen = len(published)
        await eventually(lambda: len(published) >= seen + 2)
        await stop(task)
    assert source.counters.lost_reports == 3
    assert any(p.degraded for p in published[seen - 1 :])
    assert not published[-1].degraded  # degraded marks the publication that covered the loss, then clears


async def test_unreachable_pigpiod_raises_a_clear_error() -> None:
    with socket.socket() as placeholder:
        placeholder.bind(("127.0.0.1", 0))
        port = placeholder.getsockname()[1]  # bound, never listening: connections are refused
        source = PigpioEncoders(EncodersConfig(), PigpiodConfig(port=port))
        with pytest.raises(PigpiodUnavailableError, match=f"not reachable at 127.0.0.1:{port}"):
            await source.run(lambda ticks: None)


async def test_a_lost_connection_is_retried_and_reported_degraded() -> None:
    encoders = EncodersConfig()
    first = await VirtualPigpiod().open()
    port = first.port
    source = PigpioEncoders(encoders, PigpiodConfig(port=port, reconnect_max_s=0.1))
    published: list[WheelTicks] = []
    task = asyncio.create_task(source.run(published.append))
    await eventually(lambda: source.connected)
    drive_wheels(first, encoders, [[1] * 4, [], [], []])
    await eventually(lambda: source.ticks[0] == 4)
    await first.aclose()
    await eventually(lambda: not source.connected)
    async with VirtualPigpiod(port=port) as second:
        await eventually(lambda: source.connected)
        seen = len(published)
        drive_wheels(second, encoders, [[1] * 4, [], [], []])
        await eventually(lambda: source.ticks[0] == 8)  # counting carries on from where it was
        await eventually(lambda: len(published) > seen)
        await stop(task)
    assert source.counters.reconnects == 1
    assert any(p.degraded for p in published)


def test_the_per_edge_callback_baseline_counts_the_same() -> None:
    encoders = EncodersConfig()
    with VirtualPigpiod() as server:
        baseline = CallbackEncoders(encoders, PigpiodConfig(port=server.port))
        try:
            drive_wheels(server, encoders, MOVES)
            expected = [_count_from(2, m, "x4") for m in MOVES]
            wait_until(lambda: baseline.decoder.counts == expected)
        finally:
            baseline.close()


async def test_a_cancellation_that_comes_as_the_stream_breaks_ends_the_task() -> None:
    async with VirtualPigpiod() as server:
        source = PigpioEncoders(EncodersConfig(), PigpiodConfig(port=server.port, reconnect_max_s=0.1))
        task = asyncio.create_task(source.run(lambda ticks: None))
        await eventually(lambda: source.connected)
        # what the daemon meets when it stops with the virtual robot: the stream breaks and the task is cancelled
        # in the same loop pass
        source._lost_error = OSError("pigpiod closed the notification socket")
        source._lost.set()
        task.cancel()
        async with asyncio.timeout(20.0):  # (it reconnected forever before)
            with pytest.raises(asyncio.CancelledError):
                await task
