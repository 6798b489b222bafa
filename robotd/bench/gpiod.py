"""The gpiod back-end's decoder (raw 48-byte kernel events, numpy) beside pigpio's bulk decoder, on the same motion.

Added to `robotd bench encoders` (robotd.bench.BENCHMARK_ADDITIONS). Decoding only, in this process: what the
encoder source does with the bytes of a read, whether they came from a Pi 5's line request or pigpiod's socket.
Two per-event baselines: gpiod's own `EdgeEvent` objects handed to a Python handler, one per edge, as
`LineRequest.read_edge_events()` returns them (when the `gpiod` package is installed), and the leanest per-edge
Python possible (unpack a record, one call), which no real program beats without numpy.
"""

from __future__ import annotations

import struct
import time
from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from drivers.gpiod.encoders import DECODE_BATCH_BYTES, GpiodEncoders
from drivers.gpiod.events import EVENT_SIZE, RISING_EDGE, encode_events
from drivers.pigpiod.protocol import REPORT_SIZE, encode_reports
from drivers.virtual.event_pipe import level_change_events
from drivers.virtual.quadrature_signal import encoder_words, merge_streams
from drivers.wheels.encoders import PigpioEncoders, wiring
from drivers.wheels.quadrature import EncoderWiring
from robotd.bench.encoders import EdgeDecoder
from robotd.config.model import EncodersConfig, PigpiodConfig

BATCH = DECODE_BATCH_BYTES
"""Reads are gathered into batches of this size before decoding, as the encoder source does."""
PIGPIO_READ = (1 << 16) // REPORT_SIZE * REPORT_SIZE
LOSS_EVERY = 1000
RECORD = struct.Struct("=QIIII24x")


def motion(
    edges: int, encoders: list[EncoderWiring]
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.uint32], list[int]]:
    """Microsecond ticks and level words of four wheels running forward and back (every third run backward)."""
    per_wheel = edges // len(encoders)
    streams, truth = [], []
    for index, encoder in enumerate(encoders):
        runs = np.random.default_rng(index).integers(500, 5000, size=per_wheel // 500 + 2)
        steps = np.repeat(np.where(np.arange(len(runs)) % 3 == 2, -1, 1), runs)[:per_wheel]
        positions = np.cumsum(steps)
        ticks = np.arange(per_wheel, dtype=np.int64) * (len(encoders) * 7 + 1) + index * 7  # no two wheels at once
        streams.append((ticks, encoder_words(positions, encoder.a, encoder.b), (1 << encoder.a) | (1 << encoder.b)))
        truth.append(int(positions[-1]) * encoder.sign)
    ticks, words = merge_streams(streams)
    return ticks, words, truth


def kernel_records(ticks_us: npt.NDArray[np.int64], words: npt.NDArray[np.uint32], lines: list[int]) -> bytes:
    """The motion as a line request's fd delivers it: one gpio_v2_line_event per edge, numbered from 1."""
    stamps, ids, offsets = level_change_events(ticks_us * 1000, words, 0, lines)
    line_seqnos = np.zeros(len(ids), dtype=np.int64)
    for line in lines:
        on_line = offsets == line
        line_seqnos[on_line] = np.arange(1, int(on_line.sum()) + 1)
    return encode_events(stamps, ids, offsets, np.arange(1, len(ids) + 1), line_seqnos)


def _best_of(repeats: int, run_once: Callable[[], object]) -> float:
    """The shortest of several timed runs: the one least disturbed by other work on the machine."""
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        run_once()
        best = min(best, time.perf_counter() - start)
    return best


def run(quick: bool) -> dict[str, float]:
    """Decode the same motion as kernel events (bulk, with losses, per event) and as pigpio reports."""
    encoders = EncodersConfig()
    encoder_wiring = wiring(encoders)
    lines = sorted({line for e in encoder_wiring for line in (e.a, e.b)})
    edges = 200_000 if quick else 1_000_000
    ticks, words, truth = motion(edges, encoder_wiring)
    records = kernel_records(ticks, words, lines)
    reads = [records[i : i + BATCH] for i in range(0, len(records), BATCH)]
    kept = b"".join(
        records[i : i + EVENT_SIZE]
        for i in range(0, len(records), EVENT_SIZE)
        if i % (LOSS_EVERY * EVENT_SIZE) != 500 * EVENT_SIZE
    )
    lossy_reads = [kept[i : i + BATCH] for i in range(0, len(kept), BATCH)]
    reports = encode_reports((np.arange(len(ticks)) & 0xFFFF).astype(np.uint16), ticks.astype(np.uint32), words)
    pigpio_reads = [reports[i : i + PIGPIO_READ] for i in range(0, len(reports), PIGPIO_READ)]

    def gpiod_source() -> GpiodEncoders:
        source = GpiodEncoders(encoder_wiring, encoders.counts_per_rev, decoding=encoders.decoding)
        source.begin_request(0, 0, 0.0)
        return source

    results: dict[str, tuple[int, ...]] = {}

    def gpiod_bulk(name: str, batches: list[bytes]) -> Callable[[], None]:
        def decode() -> None:
            source = gpiod_source()
            for data in batches:
                source.decode(data)
            source.decode(b"")  # anything held back for a repair
            results[name] = source.ticks

        return decode

    def pigpio_bulk() -> None:
        source = PigpioEncoders(encoders, PigpiodConfig())
        source.begin_stream(0, 0, 0.0)
        for data in pigpio_reads:
            source.decode(data)
        results["pigpio"] = source.ticks

    per_event_edges = min(edges, 200_000)

    def gpiod_per_event() -> None:
        decoder = EdgeDecoder(encoder_wiring, encoders.decoding, 0)
        for _stamp, kind, offset, _seqno, _line_seqno in RECORD.iter_unpack(records[: per_event_edges * EVENT_SIZE]):
            decoder.on_edge(offset, 1 if kind == RISING_EDGE else 0, 0)

    object_edges = min(edges, 50_000)

    def gpiod_edge_events() -> None:
        import gpiod  # noqa: PLC0415 - the optional `pi5` extra; measured only where it is installed

        decoder = EdgeDecoder(encoder_wiring, encoders.decoding, 0)
        rising = gpiod.EdgeEvent.Type.RISING_EDGE
        for record in RECORD.iter_unpack(records[: object_edges * EVENT_SIZE]):
            event = gpiod.EdgeEvent(record[1], record[0], record[2], record[3], record[4])
            decoder.on_edge(event.line_offset, 1 if event.event_type is rising else 0, 0)

    try:
        objects_s: float | None = _best_of(2, gpiod_edge_events) * edges / object_edges
    except ImportError:
        objects_s = None
    bulk_s = _best_of(5, gpiod_bulk("gpiod", reads))
    lossy_s = _best_of(5, gpiod_bulk("lossy", lossy_reads))
    pigpio_s = _best_of(5, pigpio_bulk)
    per_event_s = _best_of(2, gpiod_per_event) * edges / per_event_edges
    if list(results["gpiod"]) != truth or list(results["pigpio"]) != truth:
        raise AssertionError(f"decoders disagree: gpiod {results['gpiod']}, pigpio {results['pigpio']}, truth {truth}")
    lost = edges // LOSS_EVERY
    lossy_error = sum(abs(a - b) for a, b in zip(results["lossy"], truth, strict=True))
    print(f"gpiod back-end: the same motion as {edges:,} gpio_v2_line_event records (48 bytes), "
          f"decoded {BATCH // EVENT_SIZE} at a time")  # fmt: skip
    if objects_s is not None:
        print(f"  gpiod EdgeEvent objects + call:        {objects_s:7.3f} s  ({edges / objects_s:12,.0f} edges/s)  "
              "what read_edge_events() hands a per-edge handler")  # fmt: skip
    print(f"  per-event Python path (unpack + call): {per_event_s:7.3f} s  ({edges / per_event_s:12,.0f} edges/s)")
    print(f"  bulk numpy decoder:                    {bulk_s:7.3f} s  ({edges / bulk_s:12,.0f} edges/s)  best of 5, "
          f"{per_event_s / bulk_s:.0f}x the leanest per-event path; counts exact")  # fmt: skip
    print(f"  bulk, 1 event in {LOSS_EVERY} lost:            {lossy_s:7.3f} s  ({edges / lossy_s:12,.0f} edges/s)  "
          f"{lost:,} gaps repaired, count error {lossy_error}")  # fmt: skip
    print(f"  pigpio's bulk decoder, same motion:    {pigpio_s:7.3f} s  ({edges / pigpio_s:12,.0f} edges/s)  "
          f"12-byte reports in 64 KiB reads; gpiod/pigpio {pigpio_s / bulk_s:.2f}")  # fmt: skip
    return {
        **({"gpiod_edge_event_objects_edges_per_s": edges / objects_s} if objects_s is not None else {}),
        "gpiod_bulk_edges_per_s": edges / bulk_s,
        "gpiod_lossy_edges_per_s": edges / lossy_s,
        "gpiod_lossy_count_error": float(lossy_error),
        "gpiod_per_event_edges_per_s": edges / per_event_s,
        "pigpio_bulk_same_motion_edges_per_s": edges / pigpio_s,
    }
