"""The sans-I/O decoder of raw gpio_v2_line_event records: fed whole, byte by byte and split anywhere."""

from __future__ import annotations

import random

import numpy as np
import pytest
from gpiod_support import RECORD, initial_word, pack, walk_records
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.gpiod.events import EVENT_SIZE, EdgeEventDecoder, decode_events, encode_events, levels_after_events
from drivers.gpiod.gaps import SeqnoGaps
from drivers.wheels.quadrature import EncoderWiring, QuadratureDecoder
from robotd.bench import BENCHMARK_ADDITIONS
from robotd.bench.gpiod import kernel_records, motion

WIRING = [EncoderWiring(5, 6), EncoderWiring(13, 19, -1), EncoderWiring(26, 16), EncoderWiring(20, 21)]
MOVES = [[1] * 300 + [-1] * 120 + [1] * 3, [-1] * 257, [1, -1] * 60 + [1] * 9, [1] * 1000]


def decoder(start: int = 0) -> EdgeEventDecoder:
    return EdgeEventDecoder(WIRING, "x4", initial_word(WIRING, start), origin_ns=0)


def test_records_have_the_kernel_layout() -> None:
    data = encode_events([123456789012], [2], [17], [5], [3])
    assert len(data) == EVENT_SIZE == 48
    assert data == RECORD.pack(123456789012, 2, 17, 5, 3)
    event = decode_events(data + b"\x01\x02")[0]  # a trailing partial record is not a record
    assert (int(event["timestamp_ns"]), int(event["id"]), int(event["offset"]), int(event["seqno"])) == (
        123456789012,
        2,
        17,
        5,
    )


def test_counts_of_a_known_walk_fed_whole() -> None:
    data, net = walk_records(WIRING, MOVES)
    decoded = decoder()
    assert decoded.feed(data) == 0
    assert list(decoded.quadrature.counts) == [n * e.sign for n, e in zip(net, WIRING, strict=True)]
    assert decoded.events == sum(len(m) for m in MOVES)
    assert sum(decoded.quadrature.illegal) == 0


def test_the_same_counts_byte_by_byte_and_at_random_splits() -> None:
    data, _ = walk_records(WIRING, MOVES)
    whole = decoder()
    whole.feed(data)
    one_byte = decoder()
    for i in range(4800):  # the first hundred records a byte at a time, then the rest at once
        one_byte.feed(data[i : i + 1])
    one_byte.feed(data[4800:])
    rng = random.Random(7)
    cuts = sorted(rng.sample(range(1, len(data)), 200))
    split = decoder()
    for begin, end in zip([0, *cuts], [*cuts, len(data)], strict=True):
        split.feed(data[begin:end])
    for other in (one_byte, split):
        assert list(other.quadrature.counts) == list(whole.quadrature.counts)
        assert other.events == whole.events


def test_event_times_land_on_the_decoder_time_line_in_microseconds() -> None:
    origin = 5_000_000_000
    decoded = EdgeEventDecoder(WIRING, "x4", 0, origin_ns=origin)
    a, b = WIRING[0].a, WIRING[0].b
    decoded.feed(pack(origin + 2_500_999, True, a, 1, 1) + pack(origin + 3_000_000, True, b, 2, 1))
    assert decoded.quadrature.counts[0] == 2
    assert decoded.quadrature.last_edge_us[0] == 3000
    assert decoded.to_ticks_us(origin + 7_000_000) == 7000


def _records(data: bytes) -> list[bytes]:
    return [data[i : i + EVENT_SIZE] for i in range(0, len(data), EVENT_SIZE)]


@pytest.mark.parametrize("dropped", [0, 10, 11, 38])
def test_one_dropped_event_is_counted_and_costs_no_count(dropped: int) -> None:
    data, net = walk_records(WIRING, MOVES)
    records = _records(data)
    kept = records[:dropped] + records[dropped + 1 :]  # the kernel dropped one: its seqno is missing
    decoded = decoder()
    assert decoded.feed(b"".join(kept)) == 1
    assert decoded.lost == 1
    assert list(decoded.quadrature.counts) == [n * e.sign for n, e in zip(net, WIRING, strict=True)]
    assert sum(decoded.quadrature.illegal) == 0


def test_a_line_waiting_for_its_next_event_in_a_later_read_is_put_right_then() -> None:
    data, _ = walk_records(WIRING[:1], [[1] * 40])  # one wheel: A and B take turns
    records = _records(data)
    decoded = EdgeEventDecoder(WIRING[:1], "x4", 0, origin_ns=0)
    decoded.feed(b"".join(records[:10]))
    assert decoded.feed(records[11]) == 0  # event 11 (A falls) was dropped; A's next event is in the next read
    held = decoded.holding
    decoded.feed(b"".join(records[12:]))
    assert (held, decoded.holding) == (True, False)
    assert decoded.lost == 1
    assert decoded.quadrature.counts[0] == 40
    truth = EdgeEventDecoder(WIRING[:1], "x4", 0, origin_ns=0)
    truth.feed(data)
    assert decoded.levels == truth.levels


def test_a_held_batch_is_decoded_by_flush_when_no_event_comes() -> None:
    data, _ = walk_records(WIRING[:1], [[1] * 12])
    records = _records(data)
    decoded = EdgeEventDecoder(WIRING[:1], "x4", 0, origin_ns=0)
    decoded.feed(b"".join(records[:10] + records[11:]))  # the last A event was dropped; the wheel then stops
    held = decoded.holding
    assert decoded.flush() == 1
    assert (held, decoded.holding) == (True, False)
    assert decoded.events == 11
    # With A's next event never seen its level stays unknown: the count is right only within a quadrature cycle.
    assert abs(int(decoded.quadrature.counts[0]) - 12) < 4


def test_without_the_gap_repair_a_dropped_event_would_count_backwards() -> None:
    data, _ = walk_records(WIRING[:1], [[1] * 40])
    records = _records(data)
    kept = b"".join(records[:10] + records[11:])
    events = decode_events(kept)
    naive = levels_after_events(events["offset"], events["id"] == 1, [WIRING[0].a, WIRING[0].b], 0)
    quadrature = QuadratureDecoder(WIRING[:1], "x4", 0)
    quadrature.decode(np.arange(len(naive), dtype=np.int64), naive)
    repaired = EdgeEventDecoder(WIRING[:1], "x4", 0, origin_ns=0)
    repaired.feed(kept)
    # The stale A turns the next B edge into a backward step and swallows the A edge after it.
    assert (int(quadrature.counts[0]), int(repaired.quadrature.counts[0])) == (36, 40)


def test_sequence_gaps_across_the_32_bit_wrap() -> None:
    gaps = SeqnoGaps()
    assert gaps.check(np.array([1, 2, 3], dtype=np.uint32)) == 0
    assert gaps.check(np.array([6, 7], dtype=np.uint32)) == 2
    gaps._next = 0xFFFFFFFE  # a request that has run for hours
    assert gaps.check(np.array([0xFFFFFFFE, 0xFFFFFFFF, 0, 1], dtype=np.uint32)) == 0
    assert gaps.check(np.array([4], dtype=np.uint32)) == 2
    assert gaps.lost == 4
    gaps.restart()
    assert gaps.check(np.array([1], dtype=np.uint32)) == 0


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.tuples(st.sampled_from([3, 4, 9, 31]), st.booleans()), max_size=40),
    st.integers(min_value=0, max_value=0xFFFFFFFF),
)
def test_levels_after_events_match_setting_each_bit_in_turn(events: list[tuple[int, bool]], initial: int) -> None:
    offsets = np.array([o for o, _ in events], dtype=np.uint32)
    rising = np.array([r for _, r in events], dtype=bool)
    words = levels_after_events(offsets, rising, [3, 4, 9, 31], initial)
    level, expected = initial, []
    for offset, up in events:
        level = (level | 1 << offset) if up else (level & ~(1 << offset))
        expected.append(level)
    assert [int(w) for w in words] == expected


@settings(max_examples=40, deadline=None)
@given(st.data())
def test_counts_stay_exact_when_each_lost_line_shows_again_before_the_next_loss(data: st.DataObject) -> None:
    steps = data.draw(st.integers(min_value=20, max_value=80))
    moves = [data.draw(st.lists(st.sampled_from([1, -1]), min_size=steps, max_size=steps)) for _ in WIRING]
    records_data, net = walk_records(WIRING, moves)
    records = _records(records_data)
    lines = [RECORD.unpack(r)[2] for r in records]
    # What the repair promises (drivers.gpiod.gaps): one loss per gap, and the line that lost an edge has an event
    # of its own before the next loss. Past that a loss may alias, which the degraded flag reports.
    drops: list[int] = []
    for index in sorted(set(data.draw(st.lists(st.integers(0, len(records) - 1), max_size=6)))):
        if drops and (index == drops[-1] + 1 or lines[drops[-1]] not in lines[drops[-1] + 1 : index]):
            continue
        if lines[index] in lines[index + 1 :]:
            drops.append(index)
    kept = b"".join(r for i, r in enumerate(records) if i not in drops)
    decoded = decoder()
    split = data.draw(st.integers(0, len(kept) // EVENT_SIZE)) * EVENT_SIZE
    lost = decoded.feed(kept[:split]) + decoded.feed(kept[split:]) + decoded.flush()
    assert lost == decoded.lost == len(drops)
    assert list(decoded.quadrature.counts) == [n * e.sign for n, e in zip(net, WIRING, strict=True)]


def test_the_benchmarks_kernel_records_decode_to_the_motions_counts() -> None:
    wiring = [EncoderWiring(5, 6), EncoderWiring(13, 19), EncoderWiring(26, 16), EncoderWiring(20, 21, -1)]
    ticks, words, truth = motion(8000, wiring)
    records = kernel_records(ticks, words, sorted({line for e in wiring for line in (e.a, e.b)}))
    decoded = EdgeEventDecoder(wiring, "x4", 0, origin_ns=0)
    assert decoded.feed(records) == 0
    assert decoded.events == 8000
    assert list(decoded.quadrature.counts) == truth
    assert "robotd.bench.gpiod" in BENCHMARK_ADDITIONS["encoders"]  # `robotd bench encoders` runs it
