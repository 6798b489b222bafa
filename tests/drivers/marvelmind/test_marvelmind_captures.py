"""The real 2016 hedgehog captures give exactly the facts of their README, however the stream is cut."""

from __future__ import annotations

import itertools
import random
import struct

import pytest
from marvelmind_support import capture, chunkings, parse_reads

from drivers.marvelmind.crc import crc16_modbus
from drivers.marvelmind.events import Position, StationaryBeacons
from drivers.marvelmind.protocol import MarvelmindParser

CLEAN = "clean_capture_2016.bin"
CORRUPTED = "corrupted_capture_2016.bin"
BEACON_FRAME_OFFSET = 2185  # README: the one 0x0002 frame (8 bytes); every other frame is 0x0001 (23 bytes)


def clean_frame_boundaries(data: bytes) -> list[bytes]:
    """The clean capture cut into its frames from the README's layout, independently of the parser."""
    frames, offset = [], 0
    while offset < len(data):
        length = 8 if offset == BEACON_FRAME_OFFSET else 23
        frames.append(data[offset : offset + length])
        offset += length
    return frames


def test_clean_capture_has_142_positions_and_one_beacon_list() -> None:
    events, counters = parse_reads([capture(CLEAN)])
    positions = [e for e in events if isinstance(e, Position)]
    beacons = [e for e in events if isinstance(e, StationaryBeacons)]
    assert len(positions) == 142
    assert len(beacons) == 1
    assert beacons[0].beacons == ()
    assert counters.frames_by_code == {0x0001: 142, 0x0002: 1}
    assert (counters.junk_bytes, counters.crc_failures, counters.size_rejections) == (0, 0, 0)


def test_clean_capture_first_fix() -> None:
    first = parse_reads([capture(CLEAN)])[0][0]
    assert isinstance(first, Position)
    assert first.timestamp == 5542
    assert (first.x, first.y, first.z) == pytest.approx((0.07, -0.16, 1.56), abs=1e-12)
    assert first.flags == 0
    assert first.address == 0
    assert first.timestamp_s == pytest.approx(5542 / 64)  # flags bit 1 clear: 1/64 s units


def test_clean_capture_timestamps_run_at_about_16_hz() -> None:
    positions = [e for e in parse_reads([capture(CLEAN)])[0] if isinstance(e, Position)]
    stamps = [p.timestamp for p in positions]
    assert stamps[0] == 5542
    assert stamps[-1] == 6097
    assert {b - a for a, b in itertools.pairwise(stamps)} <= {3, 4, 5}
    last = positions[-1]
    assert (last.x, last.y, last.z) == pytest.approx((0.24, -0.24, 1.55), abs=1e-12)


def test_clean_capture_frames_agree_with_an_independent_reading() -> None:
    """Each position equals the README layout decoded with struct, frame by frame."""
    data = capture(CLEAN)
    positions = [e for e in parse_reads([data])[0] if isinstance(e, Position)]
    expected = []
    for frame in clean_frame_boundaries(data):
        assert crc16_modbus(frame) == 0
        if frame[2] == 0x01:
            timestamp, x, y, z = struct.unpack_from("<I3h", frame, 5)
            expected.append((timestamp, x / 100, y / 100, z / 100))
    assert [(p.timestamp, p.x, p.y, p.z) for p in positions] == expected


def test_corrupted_capture_gives_141_frames_and_49_junk_bytes() -> None:
    events, counters = parse_reads([capture(CORRUPTED)])
    assert counters.frames_by_code == {0x0001: 140, 0x0002: 1}
    assert counters.junk_bytes == 49
    assert counters.crc_failures >= 1
    assert len(events) == 141


def test_corrupted_capture_recovers_only_real_frames() -> None:
    clean = {(e.timestamp, e.x, e.y, e.z) for e in parse_reads([capture(CLEAN)])[0] if isinstance(e, Position)}
    corrupted = [e for e in parse_reads([capture(CORRUPTED)])[0] if isinstance(e, Position)]
    assert all((e.timestamp, e.x, e.y, e.z) in clean for e in corrupted)


@pytest.mark.parametrize("name", [CLEAN, CORRUPTED])
def test_every_chunking_gives_identical_results(name: str) -> None:
    data = capture(name)
    results = {how: parse_reads(reads) for how, reads in chunkings(data).items()}
    reference = results.pop("whole")
    for how, result in results.items():
        assert result == reference, how


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_junk_between_frames_changes_nothing_but_the_junk_count(seed: int) -> None:
    data = capture(CLEAN)
    rng = random.Random(seed)
    pieces, junk_total = [], 0
    for frame in clean_frame_boundaries(data):
        junk = bytes(rng.choice([0xFF, 0x47, 0x00, 0x01, 0x10, rng.randrange(256)]) for _ in range(rng.randint(0, 12)))
        pieces += [junk, frame]
        junk_total += len(junk)
    noisy = b"".join(pieces)
    reference, _ = parse_reads([data])
    for how, reads in chunkings(noisy).items():
        events, counters = parse_reads(reads)
        assert events == reference, how
        assert counters.junk_bytes == junk_total, how


def test_each_frame_is_emitted_by_the_read_that_completes_it() -> None:
    data = capture(CLEAN)
    parser = MarvelmindParser()
    offset = 0
    for frame in clean_frame_boundaries(data):
        assert parser.feed(frame[:-1], arrival=float(offset)) == []
        (event,) = parser.feed(frame[-1:], arrival=float(offset + 1))
        assert event.arrival == float(offset + 1)
        offset += len(frame)
