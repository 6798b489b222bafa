"""The vectorised quadrature decoder, the edge-timed speed and the stream bookkeeping, on known sequences."""

from __future__ import annotations

import itertools

import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from wheels_support import levels_of_positions, walk

from drivers.pigpiod.notifications import SequenceGaps, TickClock
from drivers.virtual.quadrature_signal import encoder_words, merge_streams
from drivers.wheels.encoders import PigpioEncoders, wiring
from drivers.wheels.quadrature import Decoding, EdgeTimedSpeed, EncoderWiring, QuadratureDecoder
from robotd.bench.encoders import EdgeDecoder, per_edge_replay, recorded_stream
from robotd.config.model import EncodersConfig, PigpiodConfig

A, B = 4, 17
WHEEL = [EncoderWiring(A, B)]
PER_PULSE = {"x1": 1, "x2": 2, "x4": 4}


def decode(positions: list[int], decoding: Decoding, start: int = 0, sign: int = 1) -> QuadratureDecoder:
    decoder = QuadratureDecoder([EncoderWiring(A, B, sign)], decoding, int(levels_of_positions([start], A, B)[0]))
    ticks = np.arange(1, len(positions) + 1, dtype=np.int64) * 100
    decoder.decode(ticks, levels_of_positions(positions, A, B))
    return decoder


@pytest.mark.parametrize("decoding", ["x1", "x2", "x4"])
def test_forward_and_backward_whole_turns(decoding: Decoding) -> None:
    ten_pulses = 40  # x4 edges
    assert decode(walk(0, [1] * ten_pulses), decoding).counts[0] == 10 * PER_PULSE[decoding]
    assert decode(walk(0, [-1] * ten_pulses), decoding).counts[0] == -10 * PER_PULSE[decoding]


@pytest.mark.parametrize(
    ("decoding", "expected"),
    [
        ("x4", 3),
        ("x2", 2),
        ("x1", 1),
    ],
)
def test_partial_pulse_counts_follow_the_edges_crossed(decoding: Decoding, expected: int) -> None:
    # Positions 1, 2, 3 are states 2 (A rose), 3 (B rose), 1 (A fell): x1 sees A's rise, x2 A's rise and fall.
    assert decode([1, 2, 3], decoding).counts[0] == expected


@pytest.mark.parametrize("decoding", ["x1", "x2", "x4"])
def test_reversals_end_where_the_wheel_is(decoding: Decoding) -> None:
    moves = [1] * 13 + [-1] * 5 + [1] * 2 + [-1] * 30 + [1] * 4
    final = sum(moves)
    # Back and forth over the same edge counts +1 then -1: the count is the position, in units of the decoding.
    assert decode(walk(0, moves), decoding).counts[0] == final * PER_PULSE[decoding] // 4


def test_dithering_on_one_edge_nets_zero() -> None:
    # A glitch on A: the encoder chatters across one edge twenty times.
    assert decode([1, 0] * 20, "x4").counts[0] == 0
    assert decode([1, 0] * 20, "x1").counts[0] == 0


def test_both_channels_changing_is_illegal_and_not_counted() -> None:
    decoder = decode([1, 3, 4, 6], "x4")  # 1->3 and 4->6 skip a state: both channels changed
    assert decoder.illegal[0] == 2
    assert decoder.counts[0] == 2  # only 0->1 and 3->4 are real steps; a skipped state is never guessed


def test_direction_sign_flips_the_count() -> None:
    assert decode(walk(0, [1] * 8), "x4", sign=-1).counts[0] == -8


def _walks_in_one_stream(
    wiring: list[EncoderWiring], moves: list[list[int]], step_us: int
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.uint32], list[int]]:
    """Each encoder walking its moves one step every `step_us` (each 10 us after the one before it), merged into one
    bank stream: its ticks and level words, and each encoder's last step's tick."""
    streams = []
    for index, (encoder, wheel_moves) in enumerate(zip(wiring, moves, strict=True)):
        positions = walk(0, wheel_moves)
        ticks = np.arange(len(positions), dtype=np.int64) * step_us + index * 10
        streams.append(
            (ticks, levels_of_positions(positions, encoder.a, encoder.b), (1 << encoder.a) | (1 << encoder.b))
        )
    ticks, levels = merge_streams(streams)
    return ticks, levels, [int(stream[0][-1]) for stream in streams]


def test_four_wheels_in_one_stream_each_count_their_own() -> None:
    wiring = [EncoderWiring(4, 17), EncoderWiring(27, 22), EncoderWiring(5, 6), EncoderWiring(2, 3, -1)]
    ticks, levels, _ = _walks_in_one_stream(wiring, [[1] * 50, [-1] * 30, [1, -1] * 10, [1] * 7], 40)
    decoder = QuadratureDecoder(wiring, "x4", 0)
    decoder.decode(ticks, levels)
    assert decoder.counts == [50, -30, 0, -7]
    assert decoder.illegal == [0, 0, 0, 0]


def test_more_than_four_wheels_are_decoded_four_at_a_time_each_its_own() -> None:
    wiring = [EncoderWiring(2 * k + 2, 2 * k + 3, -1 if k == 4 else 1) for k in range(6)]  # GPIOs 2-13
    moves = [[1] * 50, [-1] * 30, [1, -1] * 10, [1] * 7, [1] * 21, [-1] * 3 + [1] * 12]
    ticks, levels, last_ticks = _walks_in_one_stream(wiring, moves, 60)
    decoder = QuadratureDecoder(wiring, "x4", 0)
    decoder.decode(ticks[:100], levels[:100])  # two batches: the second group's state carries over too
    decoder.decode(ticks[100:], levels[100:])
    assert decoder.counts == [50, -30, 0, 7, -21, 9]
    assert decoder.illegal == [0] * 6
    assert decoder.last_edge_us == last_ticks  # every wheel's last step was an edge


@settings(max_examples=60, deadline=None)
@given(
    moves=st.lists(st.sampled_from([1, -1]), min_size=1, max_size=400),
    cuts=st.lists(st.integers(0, 400), max_size=6),
    decoding=st.sampled_from(["x1", "x2", "x4"]),
)
def test_batches_cut_anywhere_agree_with_the_per_edge_decoder(
    moves: list[int], cuts: list[int], decoding: Decoding
) -> None:
    positions = walk(0, moves)
    levels = encoder_words(positions, A, B)
    ticks = np.arange(len(levels), dtype=np.int64)
    bulk = QuadratureDecoder(WHEEL, decoding, 0)
    bounds = [0, *sorted(min(c, len(levels)) for c in cuts), len(levels)]
    for low, high in itertools.pairwise(bounds):
        bulk.decode(ticks[low:high], levels[low:high])
    per_edge = EdgeDecoder(WHEEL, decoding, 0)
    previous = 0
    for level in levels.tolist():
        for gpio in (A, B):
            if (level ^ previous) >> gpio & 1:
                per_edge.on_edge(gpio, level >> gpio & 1, 0)
        previous = level
    assert bulk.counts[0] == per_edge.counts[0] == expected_count(positions[-1], decoding)


def expected_count(position: int, decoding: str) -> int:
    """The count at an x4 position: whole pulses, plus the counted edges crossed within the last partial pulse."""
    phase = position % 4  # positions 1, 2, 3 of a pulse: A rose, B rose, A fell
    partial = {"x4": phase, "x2": [0, 1, 1, 2][phase], "x1": [0, 1, 1, 1][phase]}[decoding]
    return position // 4 * PER_PULSE[decoding] + partial


def test_speed_from_edge_times_is_exact_at_constant_rate() -> None:
    decoder = QuadratureDecoder(WHEEL, "x4", 0)
    speed = EdgeTimedSpeed(1, stale_after_us=20_000)
    # 2000 counts/s: an edge every 500 us, published every 10 ms.
    edge_ticks = np.arange(1, 200, dtype=np.int64) * 500
    levels = encoder_words(np.arange(1, 200), A, B)
    estimates = []
    for window_end in range(10_000, 100_001, 10_000):
        inside = (edge_ticks > window_end - 10_000) & (edge_ticks <= window_end)
        decoder.decode(edge_ticks[inside], levels[inside])
        estimates.append(speed.update(decoder, window_end)[0])
    assert estimates[1:] == pytest.approx([2000.0] * 9)


def test_speed_at_one_edge_per_window_and_its_decay_to_zero() -> None:
    decoder = QuadratureDecoder(WHEEL, "x4", 0)
    speed = EdgeTimedSpeed(1, stale_after_us=1_000_000)
    # 40 counts/s: an edge every 25 ms, publications every 10 ms see at most one edge.
    for index, window_end in enumerate(range(10_000, 200_001, 10_000)):
        tick = (window_end // 25_000) * 25_000
        if window_end - 10_000 < tick <= window_end:
            decoder.decode(np.array([tick], dtype=np.int64), encoder_words([tick // 25_000], A, B))
        estimate = speed.update(decoder, window_end)[0]
        if index > 6:
            assert estimate == pytest.approx(40.0)
    # The wheel stops: the speed is bounded by one count over the time since the last edge.
    last_edge = 200_000
    assert speed.update(decoder, last_edge + 100_000)[0] == pytest.approx(10.0)
    assert speed.update(decoder, last_edge + 1_000_000)[0] == pytest.approx(1.0)


def test_sequence_gaps_count_lost_reports_across_the_16_bit_wrap() -> None:
    gaps = SequenceGaps(first_seq=None)
    assert gaps.check(np.array([65533, 65534, 65535, 0, 1], dtype=np.uint16)) == 0
    assert gaps.check(np.array([4, 5], dtype=np.uint16)) == 2  # 2 and 3 missing between batches
    assert gaps.check(np.array([6, 9], dtype=np.uint16)) == 2
    assert gaps.lost == 4
    fresh = SequenceGaps()  # a new handle numbers its reports from 0
    assert fresh.check(np.array([3, 4], dtype=np.uint16)) == 3


def test_ticks_unwrap_across_2_to_the_32_and_map_to_the_monotonic_clock() -> None:
    clock = TickClock(tick=(1 << 32) - 1000, monotonic_s=50.0)
    unwrapped = clock.unwrap(np.array([(1 << 32) - 500, 100, 2000, 1990], dtype=np.uint32))
    assert unwrapped.tolist() == [500, 1100, 3000, 2990]  # a small step back stays a small step back
    # a batch's first report against the batch before: across the wrap, and a small step back
    wrapping = TickClock(tick=(1 << 32) - 10, monotonic_s=0.0)
    assert wrapping.unwrap(np.array([5], dtype=np.uint32)).tolist() == [15]
    assert wrapping.unwrap(np.array([(1 << 32) - 2, 7], dtype=np.uint32)).tolist() == [8, 17]
    assert clock.to_monotonic(1100) == pytest.approx(50.0011)
    assert clock.to_unwrapped(50.003) == 3000
    clock.anchor(tick=5000, monotonic_s=60.0)  # drift: the same tick now maps elsewhere
    assert clock.to_monotonic(clock.unwrap_one(5000)) == pytest.approx(60.0)


def test_the_benchmark_stream_decodes_exactly_both_ways() -> None:
    encoders = EncodersConfig()
    stream, truth = recorded_stream(8000, wiring(encoders))
    bulk = PigpioEncoders(encoders, PigpiodConfig())
    bulk.begin_stream(0, 0, 0.0)
    bulk.decode(stream[: 12 * 1000])
    bulk.decode(stream[12 * 1000 :])
    per_edge = EdgeDecoder(wiring(encoders), "x4", 0)
    per_edge_replay(stream, per_edge, [gpio for e in wiring(encoders) for gpio in (e.a, e.b)])
    assert list(bulk.ticks) == per_edge.counts == truth
    assert all(truth)  # every wheel moved
