"""The replay's fast paths equal the plain ones: bulk log parsing, batched wheel samples, vectorised dead reckoning,
and the whole replay against one fed event by event through the Estimator's per-event interface."""

from __future__ import annotations

import dataclasses
import io
import json
import random
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from log_reference import reference_lines

from robotd import ekf, kinematics, logfile, synthlog
from robotd.config import parse
from robotd.logfile import IpsFix, LogWriter, SensorLog, Truth
from robotd.replay import replay

GEOMETRY = kinematics.Geometry()
CPR = 6800

# lines the bulk parser must send to the per-line reader, which then accepts or reports them as json.loads would
ODD_LINES = [
    '{"t": 1.50, "type": "wheels", "ticks": [1, 2, 3, 4]}',  # valid, not in the writer's number form
    '{"t": 01.5, "type": "wheels", "ticks": [1, 2, 3, 4]}',  # leading zero: invalid JSON
    '{"t": +1.5, "type": "wheels", "ticks": [1, 2, 3, 4]}',
    '{"t": .5, "type": "wheels", "ticks": [1, 2, 3, 4]}',
    '{"t": 5., "type": "wheels", "ticks": [1, 2, 3, 4]}',
    '{"t": -.5, "type": "wheels", "ticks": [1, 2, 3, 4]}',
    '{"t": 1.e2, "type": "wheels", "ticks": [1, 2, 3, 4]}',
    '{"t": 2.6, "type": "truth", "x": 1.E2, "y": 2.0, "theta": 0.1}',
    '{"t": 2.6, "type": "truth", "x": 1E+2, "y": 2.0, "theta": -0.1e-3}',  # valid
    '{"t": 2.6, "type": "truth", "x": 1+2, "y": 2.0, "theta": 0.1}',
    '{"t": -0, "type": "wheels", "ticks": [1, 2, 3, 4]}',  # the integer -0 is 0, not -0.0
    '{"t": 1e400, "type": "wheels", "ticks": [1, 2, 3, 4]}',
    '{"t": 2.5, "type": "wheels", "ticks": [1, 2, 3.0, 4]}',  # a tick that is not an integer
    '{"t": 2.5, "type": "wheels", "ticks": [1, 2, 3, 1e3]}',
    '{"t": 2.5, "type": "wheels", "ticks": [1, 2, 3, 007]}',
    '{"t": 2.5, "type": "wheels", "ticks": [1, 2, 3]}',
    '{"t": 2.5, "type": "wheels", "ticks": [1, 2, 3, 4, 5]}',
    '{"t": 2.5, "type": "wheels", "ticks": [1, 2, 3, true]}',
    '{"t": NaN, "type": "wheels", "ticks": [1, 2, 3, 4]}',
    '{"t": 2.5, "type": "wheels", "ticks": [1, 2, 3, 4]} trailing',
    '{"t": 2.5, "type": "wheels", "ticks": [1, 2, 3, 4], "extra": 1}',
    '{"t": {"t": 2.5, "type": "wheels", "ticks": [1, 2, 3, 4]}]}',
    '{"t": 2.6, "type": "truth", "x": 1.0, "theta": 0.1, "y": 2.0}',  # keys in another order
    '{"t": 2.6, "type": "truth", "x": 1.0, "y": 2.0}',  # no heading
    '{"t": 2.6, "type": "truth", "x": 1.0, "y": 2.0, "theta": 0.1}\r',
    '{"t": 2.7, "type": "ips", "x": 1.0, "y": 2.0, "z": 0.0, "t_meas": Infinity}',
    '{"t": 2.7, "type": "ips", "x": 1.0, "y": 2.0, "z": 0.0}',
    '{"t": 2.7, "type": "ips", "x": 1.0, "y": 2.0, "z": 0.0, "t_meas": 2.6\x02}',
    '{"t": 2.8, "type": "lidar", "ranges": []}',
    '{"t"1: 2.5, "type": "wheels", "ticks": [1, 2, 3, 4]}',  # number characters inside a constant
    '{"t": 2.5, "type": "wheels", "ticks": [1,5 2, 3, 4]}',
    '1{"t": 2.5, "type": "wheels", "ticks": [1, 2, 3, 4]}',
    '{"t": 2.5, "type": "wheels", "ticks": [1, 2, 3, 4]}5',
    '{"t": 2.6, "type": "truth", "x": 1.0, 2"y": , "theta": 0.1}',  # and a number's place left empty
    "{not json",
    "[1, 2]",
    "",
    "   ",
]


def _canonical_lines(seed: int) -> list[str]:
    meta, events = synthlog.generate(synthlog.SynthSpec(loops=1, side_m=0.5, ips_offset_m=(0.1, -0.05)), seed)
    buffer = io.StringIO()
    writer = LogWriter(buffer, meta)
    for event in events:
        writer.write(event)
    return buffer.getvalue().splitlines(keepends=True)


def _same_events(a: list[logfile.Event], b: list[logfile.Event]) -> bool:
    def key(event: logfile.Event) -> tuple[object, ...]:
        values = dataclasses.astuple(event)
        # NaN != NaN, and -0.0 == 0.0: compare floats by their text, which tells both apart
        return (type(event), *(repr(v) for v in values))

    return [key(e) for e in a] == [key(e) for e in b]


def _assert_same(parsed: SensorLog, reference: SensorLog) -> None:
    assert _same_events(parsed.events, reference.events)
    assert parsed.problems == reference.problems
    assert parsed.unknown_types == reference.unknown_types
    assert parsed.meta == reference.meta


@pytest.mark.parametrize("odd", ODD_LINES)
def test_each_odd_line_among_standard_ones_is_read_as_json_would(odd: str) -> None:
    lines = _canonical_lines(23)
    lines.insert(len(lines) // 2, odd + "\n")
    _assert_same(logfile.parse_lines(lines), reference_lines(lines))


def test_bulk_parsing_equals_json_line_by_line_with_odd_lines_mixed_in(tmp_path: Path) -> None:
    lines = _canonical_lines(21)
    rng = random.Random(4)
    mixed = list(lines)
    for odd in ODD_LINES:
        mixed.insert(rng.randrange(1, len(mixed)), odd + "\n")
    reference = reference_lines(mixed)
    assert len(reference.problems) >= 15  # the odd lines really are odd
    _assert_same(logfile.parse_lines(mixed), reference)
    _assert_same(logfile.parse_lines([line.rstrip("\n") for line in mixed]), reference_lines(mixed))
    path = tmp_path / "mixed.jsonl"
    path.write_text("".join(mixed).rstrip("\n"), encoding="utf-8")  # and a last line without its newline
    _assert_same(logfile.read_log(path), reference)
    columns = logfile.read_log(path).columns()
    assert columns.time_span() == (reference.events[0].t, reference.events[-1].t)


def test_a_log_of_standard_lines_takes_the_bulk_path_and_round_trips(tmp_path: Path) -> None:
    lines = _canonical_lines(22)
    path = tmp_path / "log.jsonl"
    path.write_text("".join(lines), encoding="utf-8")
    log = logfile.read_log(path)
    _assert_same(log, reference_lines(lines))
    columns = log.columns()
    assert len(columns.wheels_t) == sum(1 for line in lines if '"wheels"' in line)
    assert "".join(logfile.encode(e) + "\n" for e in log.events) == "".join(lines[1:])


@settings(max_examples=80, deadline=None)
@given(
    edits=st.lists(
        st.tuples(st.integers(0, 10**6), st.integers(0, 10**6), st.sampled_from(list('0-+.eE, "[]{}x\x01:'))),
        min_size=1,
        max_size=4,
    ),
    delete=st.booleans(),
)
def test_any_damage_to_standard_lines_is_read_as_json_would(edits: list[tuple[int, int, str]], delete: bool) -> None:
    lines = [
        '{"t": 0.01, "type": "wheels", "ticks": [0, -3, 12, 7]}\n',
        '{"t": 0.02, "type": "truth", "x": 0.5, "y": -1.25, "theta": 3.0}\n',
        '{"t": 0.03, "type": "ips", "x": 1.0, "y": 2.0, "z": 0.0, "t_meas": 0.01}\n',
        '{"t": 0.04, "type": "wheels", "ticks": [1, -2, 13, 8]}\n',
    ] * 3
    for line_pick, position_pick, char in edits:
        index = line_pick % len(lines)
        line = lines[index]
        position = position_pick % (len(line) - 1)
        lines[index] = line[:position] + ("" if delete else char) + line[position + 1 :]
    _assert_same(logfile.parse_lines(lines), reference_lines(lines))


def test_estimates_file_lines_are_the_specified_json(tmp_path: Path) -> None:
    from robotd.replay import write_outputs  # noqa: PLC0415

    meta, events = synthlog.generate(synthlog.SynthSpec(loops=1, side_m=0.5), 6)
    result = replay(SensorLog(meta=meta, events=events), parse(""))
    write_outputs(result, tmp_path)
    rows = [json.loads(line) for line in (tmp_path / "estimates.jsonl").read_text().splitlines()]
    assert len(rows) == len(result.ekf.t)
    for row, t, x, cov in zip(rows, result.ekf.t, result.ekf.x, result.ekf.cov, strict=True):
        assert set(row) == {"t", "x", "y", "theta", "cov"}
        assert abs(row["t"] - t) <= 5e-7
        assert abs(row["x"] - x) <= 5e-7
        assert np.allclose(row["cov"], ekf.cov_full(cov), rtol=1e-8, atol=0.0)


def test_without_truth_only_robotds_filter_runs_and_its_estimates_do_not_change() -> None:
    meta, events = synthlog.generate(synthlog.SynthSpec(loops=1, ips_offset_m=(0.1, 0.0)), 19)
    with_truth = replay(SensorLog(meta=meta, events=list(events)), parse(""))
    without = replay(SensorLog(meta=meta, events=[e for e in events if type(e) is not Truth]), parse(""))
    assert without.metrics is None
    assert without.paper.t == []  # nothing of the baselines would be written: not computed
    assert without.odometry.t == []
    assert with_truth.paper.t
    assert with_truth.odometry.t
    for name in ("t", "x", "y", "theta"):
        assert repr(getattr(without.ekf, name)) == repr(getattr(with_truth.ekf, name))
    assert np.array_equal(without.ekf.cov, with_truth.ekf.cov)
    assert without.counters == with_truth.counters
    assert repr(without.diagnostics) == repr(with_truth.diagnostics)


def test_a_log_in_unix_time_replays_as_the_same_log_from_zero() -> None:
    """Times near 1.7e9 s carry rounding of a fraction of a microsecond: the steps and outputs must not move."""
    meta, events = synthlog.generate(synthlog.SynthSpec(loops=1), 3)
    shift = 1.7e9
    moved = [
        dataclasses.replace(e, t=e.t + shift, t_meas=e.t_meas + shift)
        if isinstance(e, IpsFix)
        else dataclasses.replace(e, t=e.t + shift)
        for e in events
    ]
    base = replay(SensorLog(meta=meta, events=list(events)), parse(""))
    late = replay(SensorLog(meta=meta, events=moved), parse(""))
    assert len(late.ekf.t) == len(base.ekf.t)
    assert np.max(np.abs(np.array(late.ekf.t) - shift - np.array(base.ekf.t))) < 1e-6
    assert np.max(np.abs(np.array(late.ekf.x) - np.array(base.ekf.x))) < 1e-4
    assert np.max(np.abs(np.array(late.paper.x) - np.array(base.paper.x))) < 1e-4
