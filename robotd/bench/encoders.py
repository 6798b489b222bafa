"""Encoder decoding: bulk numpy decoder vs a per-edge pigpio callback, and 136,000 edges/s through the vpigpiod."""

from __future__ import annotations

import asyncio
import contextlib
import multiprocessing
import multiprocessing.connection
import struct
import time
from dataclasses import replace

import numpy as np
import numpy.typing as npt

from drivers.encoders import EdgeDecoder, PigpioEncoders, wiring
from drivers.pigpio_protocol import REPORT_SIZE, encode_reports
from drivers.quadrature import EncoderWiring
from drivers.sim.quadrature_signal import encoder_words, merge_streams, position_of_state
from robotd.config import EncodersConfig, PigpiodConfig

NAME = "encoders"
EDGES_PER_S = 136_000
"""Four 1700 PPR encoders decoded x4 at 5 turns a second."""
READ_SIZE = 1 << 16
REPORT = struct.Struct("<HHII")


def _wheel_positions(edges: int, seed: int) -> npt.NDArray[np.int64]:
    """A wheel's x4 position after each of its edges: runs forward and back, the way teleop drives."""
    rng = np.random.default_rng(seed)
    run_lengths = rng.integers(500, 5000, size=edges // 500 + 2)
    directions = np.repeat(np.where(np.arange(len(run_lengths)) % 3 == 2, -1, 1), run_lengths)[:edges]
    return np.cumsum(directions)


def recorded_stream(edges: int, encoders: list[EncoderWiring]) -> tuple[bytes, list[int]]:
    """A notification stream of `edges` level changes over all wheels, as pigpiod sends it; and the true counts."""
    per_wheel = edges // len(encoders)
    streams, truth = [], []
    for index, encoder in enumerate(encoders):
        positions = _wheel_positions(per_wheel, seed=index)
        # Each wheel's edges every ~29 us, offset so that two wheels never share a tick.
        ticks = np.arange(per_wheel, dtype=np.int64) * (len(encoders) * 7 + 1) + index * 7
        streams.append((ticks, encoder_words(positions, encoder.a, encoder.b), (1 << encoder.a) | (1 << encoder.b)))
        truth.append(int(positions[-1]) * encoder.sign)
    ticks, levels = merge_streams(streams)
    seq = (np.arange(len(ticks)) & 0xFFFF).astype(np.uint16)
    return encode_reports(seq, (ticks & 0xFFFFFFFF).astype(np.uint32), levels), truth


def per_edge_replay(stream: bytes, decoder: EdgeDecoder, gpios: list[int]) -> None:
    """Dispatch a stream one callback per edge, as pigpio's callback thread does for `pi.callback` users."""
    watched = [(gpio, 1 << gpio) for gpio in gpios]
    last = 0
    for offset in range(0, len(stream), REPORT_SIZE):
        _seq, flags, tick, level = REPORT.unpack_from(stream, offset)
        if flags:
            continue
        changed = level ^ last
        last = level
        for gpio, bit in watched:
            if changed & bit:
                decoder.on_edge(gpio, 1 if level & bit else 0, tick)


def _decode_ratio(quick: bool, encoders: EncodersConfig) -> dict[str, float]:
    encoder_wiring = wiring(encoders)
    edges = 400_000 if quick else 2_000_000
    stream, truth = recorded_stream(edges, encoder_wiring)

    bulk = PigpioEncoders(encoders, PigpiodConfig())
    start = time.perf_counter()
    bulk.begin_stream(0, 0, 0.0)
    for offset in range(0, len(stream), READ_SIZE - READ_SIZE % REPORT_SIZE):
        bulk.decode(stream[offset : offset + READ_SIZE - READ_SIZE % REPORT_SIZE])
    bulk_s = time.perf_counter() - start

    per_edge = EdgeDecoder(encoder_wiring, encoders.decoding, 0)
    gpios = [gpio for encoder in encoder_wiring for gpio in (encoder.a, encoder.b)]
    start = time.perf_counter()
    per_edge_replay(stream, per_edge, gpios)
    per_edge_s = time.perf_counter() - start

    if list(bulk.ticks) != truth or per_edge.counts != truth:
        raise AssertionError(f"decoders disagree: bulk {bulk.ticks}, per-edge {per_edge.counts}, truth {truth}")
    ratio = per_edge_s / bulk_s
    print(f"recorded stream: {edges:,} edges, 4 wheels x4, counts exact in both decoders")
    print(f"  per-edge callback path: {per_edge_s:7.3f} s  ({edges / per_edge_s:12,.0f} edges/s)")
    print(f"  bulk numpy decoder:     {bulk_s:7.3f} s  ({edges / bulk_s:12,.0f} edges/s)")
    print(f"  bulk is {ratio:.1f}x faster (target >= 20x): {'PASS' if ratio >= 20 else 'FAIL'}")
    return {
        "per_edge_edges_per_s": edges / per_edge_s,
        "bulk_edges_per_s": edges / bulk_s,
        "bulk_speedup": ratio,
    }


def _feeder(
    control: multiprocessing.connection.Connection, encoder_wiring: list[EncoderWiring], seconds: float
) -> None:
    """Child process: a virtual pigpiod driving four encoders at EDGES_PER_S in real time, in 2 ms batches."""
    from drivers.sim.vpigpiod import VirtualPigpiod  # noqa: PLC0415

    with VirtualPigpiod() as server:
        control.send(server.port)
        control.recv()  # the encoder source is connected and configured
        per_wheel = EDGES_PER_S / len(encoder_wiring)
        direction = [1, -1, 1, -1]
        levels = 0
        start_positions = []
        for encoder in encoder_wiring:
            a, b = server.level(encoder.a), server.level(encoder.b)
            levels |= a << encoder.a | b << encoder.b
            start_positions.append(position_of_state(a << 1 | b))
        mask = sum((1 << e.a) | (1 << e.b) for e in encoder_wiring)
        begin = time.monotonic()
        done = [0] * len(encoder_wiring)
        while True:
            now = time.monotonic()
            elapsed = min(now - begin, seconds)
            streams = []
            for index, encoder in enumerate(encoder_wiring):
                target = int(elapsed * per_wheel)
                k = np.arange(done[index] + 1, target + 1, dtype=np.int64)
                done[index] = target
                # Edge k of this wheel happens at begin + k / rate, the wheels a quarter period apart.
                ticks = server.ticks_at(begin + (k + index / len(encoder_wiring)) / per_wheel).astype(np.int64)
                positions = start_positions[index] + direction[index] * k
                bits = (1 << encoder.a) | (1 << encoder.b)
                streams.append((ticks, encoder_words(positions, encoder.a, encoder.b), bits))
            ticks, words = merge_streams(streams, levels)
            if len(ticks):
                server.drive_levels(ticks.astype(np.uint32), words, mask)
                levels = int(words[-1])
            if elapsed >= seconds:
                break
            time.sleep(max(0.0, 0.002 - (time.monotonic() - now)))
        time.sleep(0.2)  # let the server's loop write the last batch before counting what it sent
        expected = [direction[i] * done[i] * e.sign for i, e in enumerate(encoder_wiring)]
        control.send((expected, server.reports_sent, server.reports_lost, sum(done)))
        control.recv()  # the parent has read everything


async def _consume(
    encoders: EncodersConfig, port: int, control: multiprocessing.connection.Connection
) -> dict[str, float]:
    source = PigpioEncoders(encoders, PigpiodConfig(port=port))
    published: list[object] = []
    task = asyncio.create_task(source.run(published.append))
    while not source.connected:
        if task.done():
            task.result()  # raises why it could not connect
        await asyncio.sleep(0.01)
    cpu0, wall0 = time.process_time(), time.perf_counter()
    control.send("go")
    loop = asyncio.get_running_loop()
    while not await loop.run_in_executor(None, control.poll, 0.1):
        pass
    expected, sent, lost_at_source, edges = control.recv()
    deadline = time.monotonic() + 5
    while source.counters.reports < sent and time.monotonic() < deadline:
        await asyncio.sleep(0.01)
    cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await task
    control.send("done")
    counters = source.counters
    exact = list(source.ticks) == expected
    print(f"live: {edges:,} edges in {wall:.1f} s through the virtual pigpiod's socket ({edges / wall:,.0f} edges/s)")
    print(f"  reports {counters.reports:,} of {sent:,} sent, lost {counters.lost_reports + lost_at_source}, "
          f"illegal {sum(counters.illegal_transitions)}, counts {'exact' if exact else 'WRONG'} "
          f"({list(source.ticks)} vs {expected})")  # fmt: skip
    print(f"  encoder source CPU: {cpu:.2f} s for {wall:.1f} s = {100 * cpu / wall:.1f}% of one core "
          f"({1e6 * cpu / max(edges, 1):.2f} us per edge)")  # fmt: skip
    return {
        "live_edges_per_s": edges / wall,
        "live_lost_reports": float(counters.lost_reports + lost_at_source),
        "live_count_errors": float(sum(abs(a - b) for a, b in zip(source.ticks, expected, strict=True))),
        "live_cpu_percent": 100 * cpu / wall,
    }


def run(quick: bool) -> dict[str, float]:
    """Both measurements; `quick` shrinks them to a few seconds."""
    encoders = replace(EncodersConfig(), glitch_filter_us=0)
    figures = _decode_ratio(quick, encoders)
    seconds = 2.0 if quick else 30.0
    context = multiprocessing.get_context("spawn")
    parent_end, child_end = context.Pipe()
    child = context.Process(target=_feeder, args=(child_end, wiring(encoders), seconds), daemon=True)
    child.start()
    try:
        if not parent_end.poll(20):
            raise RuntimeError("the virtual pigpiod process did not start")
        port = parent_end.recv()
        figures |= asyncio.run(_consume(encoders, port, parent_end))
    finally:
        child.join(10)
        if child.is_alive():
            child.terminate()
            child.join()
    return figures
