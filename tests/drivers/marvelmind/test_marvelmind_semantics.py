"""Semantics of the parser on synthetic frames (built from the protocol tables: no public capture has these codes)."""

from __future__ import annotations

import math

import pytest

from drivers.marvelmind.events import (
    Distance,
    FixUnavailable,
    ImuFusion,
    Position,
    Quality,
    RawDistances,
    RawImu,
    StationaryBeacon,
    StationaryBeacons,
    Telemetry,
)
from drivers.marvelmind.frames import (
    build_frame,
    encode_beacons_cm,
    encode_beacons_mm,
    encode_imu_fusion,
    encode_position_cm,
    encode_position_mm,
    encode_position_mm64,
    encode_quality,
    encode_raw_distances,
    encode_raw_imu64,
    encode_telemetry,
)
from drivers.marvelmind.framing import MAX_FRAME, FrameScanner
from drivers.marvelmind.protocol import MarvelmindParser


def feed_all(parser: MarvelmindParser, *frames: bytes, arrival: float = 10.0) -> list[object]:
    return [event for frame in frames for event in parser.feed(frame, arrival)]


def test_the_documented_example_frame_is_what_the_encoder_builds() -> None:
    documented = bytes.fromhex("ff47 0100 10 a6150000 0700 f0ff 9c00 00 00 0000 0000 194a".replace(" ", ""))
    assert encode_position_cm(5542, 0.07, -0.16, 1.56, address=0, flags=0) == documented


def test_coordinates_unavailable_gives_a_fix_unavailable_event_never_a_position() -> None:
    parser = MarvelmindParser()
    (event,) = feed_all(parser, encode_position_mm(1000, 1.0, 2.0, 0.5, address=7, flags=0x03))
    assert isinstance(event, FixUnavailable)
    assert (event.address, event.timestamp, event.arrival) == (7, 1000, 10.0)
    assert not hasattr(event, "x")
    assert parser.counters.unavailable_fixes == 1


@pytest.mark.parametrize(("flags", "seconds"), [(0x02, 6.4), (0x00, 100.0)])
def test_flags_bit_1_selects_milliseconds_or_64ths_of_a_second(flags: int, seconds: float) -> None:
    (event,) = feed_all(MarvelmindParser(), encode_position_cm(6400, 0.0, 0.0, 0.0, address=1, flags=flags))
    assert isinstance(event, Position)
    assert event.timestamp_s == pytest.approx(seconds)


def test_bit_6_frames_are_another_hedgehogs_and_are_dropped() -> None:
    parser = MarvelmindParser()
    events = feed_all(parser, encode_position_mm(1, 5.0, 5.0, 0.0, address=9, flags=0x42))
    assert events == []
    assert parser.counters.other_address == 1
    assert parser.hedgehog_address is None  # bit 6 frames never teach the address


def test_auto_address_is_learnt_from_the_first_own_frame_then_filters() -> None:
    parser = MarvelmindParser("auto")
    events = feed_all(
        parser,
        encode_position_mm(1, 5.0, 5.0, 0.0, address=9, flags=0x42),  # modem relaying hedgehog 9
        encode_position_mm(2, 1.0, 1.0, 0.0, address=4),  # our own
        encode_position_mm(3, 5.0, 5.0, 0.0, address=9),  # another hedgehog without bit 6
        encode_telemetry(9, 3.9, -60),
        encode_telemetry(4, 3.7, -50),
        encode_position_mm(4, 1.1, 1.0, 0.0, address=4),
    )
    assert parser.hedgehog_address == 4
    assert [type(e).__name__ for e in events] == ["Position", "Telemetry", "Position"]
    assert all(e.address == 4 for e in events)  # type: ignore[attr-defined]
    assert parser.counters.other_address == 3


def test_a_configured_address_filters_from_the_first_frame() -> None:
    parser = MarvelmindParser(hedgehog_address=9)
    events = feed_all(parser, encode_position_mm(2, 1.0, 1.0, 0.0, address=4), encode_quality(4, 80))
    assert events == []
    assert parser.counters.other_address == 2
    (event,) = feed_all(parser, encode_position_mm(3, 1.0, 1.0, 0.0, address=9))
    assert isinstance(event, Position)


def test_a_repeated_timestamp_is_a_duplicate_and_dropped() -> None:
    parser = MarvelmindParser()
    frame = encode_position_mm(500, 1.0, 2.0, 0.0, address=1)
    events = feed_all(parser, frame, frame, encode_position_mm(501, 1.0, 2.0, 0.0, address=1))
    assert [e.timestamp for e in events] == [500, 501]  # type: ignore[attr-defined]
    assert parser.counters.duplicates == 1


def test_measurement_time_is_arrival_minus_time_shift_or_default_latency() -> None:
    parser = MarvelmindParser(default_latency_s=0.08)
    shifted, unknown = feed_all(
        parser,
        encode_position_mm(1, 0.0, 0.0, 0.0, address=1, time_shift_ms=120),
        encode_position_mm(2, 0.0, 0.0, 0.0, address=1, time_shift_ms=0),
        arrival=50.0,
    )
    assert isinstance(shifted, Position)
    assert isinstance(unknown, Position)
    assert shifted.t_meas == pytest.approx(49.88)
    assert shifted.time_shift_s == pytest.approx(0.12)
    assert unknown.t_meas == pytest.approx(49.92)


def test_millimetre_positions_and_the_speed_extension() -> None:
    parser = MarvelmindParser()
    plain, with_speed = feed_all(
        parser,
        encode_position_mm(1, -1.234, 2.5, 0.001, address=3, angle_word=900),
        encode_position_mm64(2**40, 3.0, -4.0, 0.5, address=3, velocity_mps=(0.25, -0.1, 0.0)),
    )
    assert isinstance(plain, Position)
    assert (plain.x, plain.y, plain.z) == (-1.234, 2.5, 0.001)
    assert plain.heading_rad == pytest.approx(math.radians(90.0))
    assert isinstance(with_speed, Position)
    assert with_speed.timestamp == 2**40
    assert with_speed.velocity == (0.25, -0.1, 0.0)
    assert (with_speed.x, with_speed.y, with_speed.z) == (3.0, -4.0, 0.5)


def test_an_unknown_extension_subcode_ends_the_records() -> None:
    base = encode_position_mm64(7, 1.0, 1.0, 0.0, address=3)[5:-2]
    speed = bytes([1]) + (100).to_bytes(2, "little", signed=True) * 3
    unknown_first = build_frame(0x0081, base + bytes([9]) + speed)
    (event,) = feed_all(MarvelmindParser(), unknown_first)
    assert isinstance(event, Position)
    assert event.velocity is None


def test_heading_not_applicable() -> None:
    (event,) = feed_all(MarvelmindParser(), encode_position_mm(1, 0.0, 0.0, 0.0, address=1, angle_word=0x2000 | 450))
    assert isinstance(event, Position)
    assert event.heading_rad is None


def test_stationary_beacons_in_cm_and_mm() -> None:
    beacons = (StationaryBeacon(1, 0.0, 0.0, 2.0), StationaryBeacon(2, 4.5, -0.25, 2.0))
    cm, mm = feed_all(
        MarvelmindParser(),
        encode_beacons_cm(beacons),
        encode_beacons_mm((*beacons, StationaryBeacon(3, 1.234, 0.0, 0.5, applicable=False))),
    )
    assert isinstance(cm, StationaryBeacons)
    assert cm.beacons == beacons
    assert isinstance(mm, StationaryBeacons)
    assert mm.beacons[2] == StationaryBeacon(3, 1.234, 0.0, 0.5, applicable=False)


def test_raw_imu_units_and_missing_sensors() -> None:
    (event,) = feed_all(
        MarvelmindParser(),
        encode_raw_imu64(123456789012, 5, acceleration=(0.0, 0.0, 9.80665), angular_velocity=(0.0, 0.0, 1.0)),
    )
    assert isinstance(event, RawImu)
    assert event.acceleration == pytest.approx((0.0, 0.0, 9.80665))  # 1000 mg
    assert event.angular_velocity == pytest.approx((0.0, 0.0, 1.0), abs=math.radians(0.0175))
    assert event.magnetic_field is None
    assert event.timestamp == 123456789012


def test_raw_distances_leave_out_empty_items() -> None:
    distances = (Distance(11, 2.345, True), Distance(12, 0.5, False))
    (event,) = feed_all(MarvelmindParser(), encode_raw_distances(99, 5, distances, time_shift_ms=30), arrival=2.0)
    assert isinstance(event, RawDistances)
    assert event.distances == distances
    assert event.t_meas == pytest.approx(1.97)


def test_imu_fusion_units() -> None:
    (event,) = feed_all(
        MarvelmindParser(),
        encode_imu_fusion(10, 5, position=(1.0, 2.0, 0.1), quaternion=(1.0, 0.0, 0.0, 0.0), velocity=(0.5, 0.0, 0.0)),
    )
    assert isinstance(event, ImuFusion)
    assert event.position == (1.0, 2.0, 0.1)
    assert event.quaternion == (1.0, 0.0, 0.0, 0.0)
    assert event.velocity == (0.5, 0.0, 0.0)
    assert event.acceleration is None


def test_telemetry_and_quality() -> None:
    telemetry, quality = feed_all(MarvelmindParser(), encode_telemetry(5, 3.912, -71), encode_quality(5, 87, 2))
    assert telemetry == Telemetry(10.0, 5, 3.912, -71, 0x0006)
    assert quality == Quality(10.0, 5, 87, 2, 0x0007)


def test_a_real_frame_that_starts_inside_a_rejected_one_is_found() -> None:
    """A bad header claiming 23 bytes overlaps the start of a real frame; rejecting it must not lose that frame."""
    real = encode_position_mm(77, 1.0, 2.0, 0.0, address=1)
    bad_start = bytes.fromhex("ff47010010") + bytes(5)  # 0x0001, N = 16: its CRC would sit inside `real`
    scanner = FrameScanner()
    assert scanner.feed(bad_start + real) == [(0x0011, real[5:-2])]
    assert scanner.counters.crc_failures == 1
    assert scanner.counters.junk_bytes == len(bad_start)


def test_a_frame_held_behind_a_waiting_false_header_is_emitted_when_complete() -> None:
    """A false 0x0081 header claiming 262 bytes must not delay the real frame inside its extent."""
    real = encode_position_mm(78, 1.0, 2.0, 0.0, address=1)
    parser = MarvelmindParser()
    assert parser.feed(bytes.fromhex("ff478100ff") + b"\x00" * 20 + real[:-1], arrival=1.0) == []
    (event,) = parser.feed(real[-1:], arrival=2.0)
    assert isinstance(event, Position)
    assert event.arrival == 2.0
    assert parser.counters.false_headers == 1


def test_finish_counts_an_incomplete_frame_as_junk() -> None:
    frame = encode_position_mm(1, 0.0, 0.0, 0.0, address=1)
    parser = MarvelmindParser()
    assert parser.feed(frame[:-3], arrival=1.0) == []
    assert parser.pending == len(frame) - 3
    parser.finish()
    assert (parser.counters.truncated, parser.counters.junk_bytes, parser.pending) == (1, len(frame) - 3, 0)


def test_beacon_list_size_must_match_its_count() -> None:
    good = encode_beacons_cm((StationaryBeacon(1, 0.0, 0.0, 0.0),))
    lying = build_frame(0x0002, bytes([2]) + good[6:-2])  # says 2 beacons, carries 1
    parser = MarvelmindParser()
    assert parser.feed(lying, arrival=1.0) == []
    assert parser.counters.size_rejections == 1


def test_the_buffer_stays_capped_whatever_arrives() -> None:
    parser = MarvelmindParser()
    for _ in range(200):
        parser.feed(bytes.fromhex("ff478100ff") + bytes(100), arrival=1.0)  # endless false headers
        assert parser.pending < MAX_FRAME


def test_bad_configuration_is_refused() -> None:
    with pytest.raises(ValueError, match="hedgehog_address"):
        MarvelmindParser(hedgehog_address=300)
    with pytest.raises(ValueError, match="default_latency_s"):
        MarvelmindParser(default_latency_s=-1.0)


def test_an_encoder_refuses_a_value_that_does_not_fit() -> None:
    with pytest.raises(ValueError, match="0x0001"):
        encode_position_cm(1, 400.0, 0.0, 0.0, address=1)  # 40000 cm overflows i16
