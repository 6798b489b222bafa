"""Marvelmind parser: throughput and last-byte-to-event latency against a naive byte-at-a-time parser."""

from __future__ import annotations

import itertools
import statistics
import struct
import time
from pathlib import Path

from drivers.marvelmind.crc import BYTE_TABLE
from drivers.marvelmind.events import Position
from drivers.marvelmind.frames import encode_beacons_cm, encode_position_cm
from drivers.marvelmind.protocol import MarvelmindParser

NAME = "marvelmind"
CAPTURE = Path(__file__).resolve().parents[2] / ".." / "shared" / "fixtures" / "marvelmind" / "clean_capture_2016.bin"
TRANSPORT_READ = 1024  # pyserial-asyncio-fast reads at most this much per wake-up
FRAME_READ = 23  # one 0x0001 frame per read: a hedgehog at 16 Hz over USB
TICK_S = 1 / 64  # the capture's timestamp unit (2016 firmware)
_POSITION_CM = struct.Struct("<I3hBBHH")


class NaiveByteParser:
    """The baseline: the parser style marvelmind-protocol.md criticises, written here for comparison only.

    One byte at a time, the buffer rebuilt on every byte, a frame decoded only once the next frame's first byte has
    arrived, the whole claimed length dropped after a bad frame, and flags bit 0 ignored.
    """

    def __init__(self) -> None:
        self.buffer = b""

    def feed_byte(self, byte: int) -> list[tuple[int, float, float, float]]:
        """Positions (timestamp, x, y, z) decoded after this byte."""
        self.buffer = self.buffer + bytes([byte])
        positions: list[tuple[int, float, float, float]] = []
        while True:
            start = self.buffer.find(b"\xff\x47")
            if start < 0:
                self.buffer = self.buffer[-1:]
                return positions
            self.buffer = self.buffer[start:]
            if len(self.buffer) < 5:
                return positions
            length = self.buffer[4] + 7
            if len(self.buffer) <= length:  # waits for the first byte of the next frame
                return positions
            frame, self.buffer = self.buffer[:length], self.buffer[length:]
            register = 0xFFFF
            for value in frame:
                register = (register >> 8) ^ BYTE_TABLE[(register ^ value) & 0xFF]
            if register == 0 and frame[2:4] == b"\x01\x00" and length == 23:
                stamp, x, y, z, *_ = _POSITION_CM.unpack_from(frame, 5)
                positions.append((stamp, x / 100, y / 100, z / 100))


def _capture() -> tuple[bytes, str]:
    """The clean real capture, or a synthetic stand-in of the same shape when the shared fixtures are absent."""
    if CAPTURE.exists():
        return CAPTURE.read_bytes(), "real clean capture (142 positions + 1 beacon list)"
    frames = [encode_position_cm(5542 + 4 * i, 0.07 + 0.001 * i, -0.16, 1.56, 0, flags=0) for i in range(142)]
    frames.insert(95, encode_beacons_cm(()))
    return b"".join(frames), "synthetic stand-in (shared fixtures not found)"


def _robotd_rate(stream: bytes, read_size: int) -> tuple[float, int]:
    """Seconds to parse `stream` in reads of `read_size`, and the positions found."""
    parser = MarvelmindParser()
    positions = 0
    start = time.perf_counter()
    for offset in range(0, len(stream), read_size):
        positions += len(parser.feed(stream[offset : offset + read_size], 0.0))
    return time.perf_counter() - start, positions


def _naive_rate(stream: bytes) -> tuple[float, int]:
    parser = NaiveByteParser()
    positions = 0
    start = time.perf_counter()
    for byte in stream:
        positions += len(parser.feed_byte(byte))
    return time.perf_counter() - start, positions


def _robotd_latencies(capture: bytes, rounds: int) -> list[float]:
    """Seconds from feeding a frame's last byte to holding its event, for every frame of the capture."""
    parser = MarvelmindParser()
    latencies = []
    clock = time.perf_counter
    for _ in range(rounds):
        offset = 0
        while offset < len(capture):
            length = capture[offset + 4] + 7
            parser.feed(capture[offset : offset + length - 1], 0.0)
            start = clock()
            events = parser.feed(capture[offset + length - 1 : offset + length], 0.0)
            latencies.append(clock() - start)
            assert len(events) == 1
            offset += length
    return latencies


def _naive_latencies(capture: bytes) -> tuple[list[float], int]:
    """How long the baseline holds each position (to the next frame, by the beacon's clock), and how many it loses."""
    parser = NaiveByteParser()
    emitted = [position[0] for byte in capture for position in parser.feed_byte(byte)]
    stamps = [stamp for stamp, *_ in _all_positions(capture)]
    held = [(after - before) * TICK_S for before, after in itertools.pairwise(stamps) if before in emitted]
    return held, len(stamps) - len(emitted)


def _all_positions(capture: bytes) -> list[tuple[int, float, float, float]]:
    parser = MarvelmindParser()
    return [(e.timestamp, e.x, e.y, e.z) for e in parser.feed(capture, 0.0) if isinstance(e, Position)]


def run(quick: bool) -> dict[str, float]:
    """Print and return throughput (MB/s, frames/s) and latency of robotd's parser and of the naive baseline."""
    capture, source = _capture()
    target = 1_000_000 if quick else 10_000_000
    stream = capture * (target // len(capture) + 1)
    naive_stream = stream[: (200_000 if quick else 1_000_000)]
    small_stream = stream[: (500_000 if quick else 2_000_000)]
    print(f"input: {source}, repeated to {len(stream) / 1e6:.1f} MB")

    seconds, positions = _robotd_rate(stream, TRANSPORT_READ)
    robotd_mbps, robotd_fps = len(stream) / seconds / 1e6, positions / seconds
    print(f"robotd, {TRANSPORT_READ}-byte reads: {robotd_mbps:.2f} MB/s, {robotd_fps:,.0f} positions/s")
    small_seconds, _ = _robotd_rate(small_stream, FRAME_READ)
    frame_read_mbps = len(small_stream) / small_seconds / 1e6
    print(
        f"robotd, {FRAME_READ}-byte reads (a frame each), {len(small_stream) / 1e6:.1f} MB: {frame_read_mbps:.2f} MB/s"
    )

    naive_seconds, naive_positions = _naive_rate(naive_stream)
    naive_mbps, naive_fps = len(naive_stream) / naive_seconds / 1e6, naive_positions / naive_seconds
    print(
        f"baseline (naive byte-at-a-time parser), {len(naive_stream) / 1e6:.1f} MB: {naive_mbps:.2f} MB/s, "
        f"{naive_fps:,.0f} positions/s"
    )
    print(f"throughput ratio robotd / baseline: {robotd_mbps / naive_mbps:.1f}x")

    latencies = sorted(_robotd_latencies(capture, 3 if quick else 20))
    median = statistics.median(latencies)
    p99 = latencies[int(0.99 * (len(latencies) - 1))]
    print(f"robotd, last byte to event: median {median * 1e6:.1f} us, p99 {p99 * 1e6:.1f} us")
    held, lost = _naive_latencies(capture)
    naive_median = statistics.median(held)
    print(
        f"baseline, last byte to event: median {naive_median * 1e3:.1f} ms (it waits for the next frame's first byte, "
        f"timed by the capture's timestamps), {lost} position(s) of the capture never emitted; "
        f"ratio {naive_median / median:,.0f}x"
    )
    return {
        "robotd_mbps": robotd_mbps,
        "robotd_positions_per_s": robotd_fps,
        "robotd_frame_reads_mbps": frame_read_mbps,
        "baseline_mbps": naive_mbps,
        "baseline_positions_per_s": naive_fps,
        "throughput_ratio": robotd_mbps / naive_mbps,
        "latency_median_s": median,
        "latency_p99_s": p99,
        "baseline_latency_median_s": naive_median,
        "latency_ratio": naive_median / median,
    }
