"""The sensor log format through msgspec: what the writer writes reads back, and every bad line is one reported
problem with its line number, never an exception."""

from __future__ import annotations

import io
import math
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from sim_logs import sim_config, simulated_text

from robotd.logs import sensorlog
from robotd.logs.events import rounded
from robotd.logs.sensorlog import IpsFix, LogWriter, Meta, Truth, TwistSample, Wheels, encode, parse_lines, read_log

GOOD = '{"t": 0.5, "type": "wheels", "ticks": [1, 2, 3, 4]}'

# hostile or damaged lines, and what the report must say about each (a part of the reason)
BAD_LINES = [
    ("{not json", "malformed"),
    ("[1, 2]", "Expected `object`, got `array`"),
    ('"wheels"', "Expected `object`, got `str`"),
    ('{"t": NaN, "type": "wheels", "ticks": [1, 2, 3, 4]}', "malformed"),  # JSON has no NaN
    ('{"t": Infinity, "type": "ips_lost"}', "malformed"),
    ('{"t": 1e300, "type": "ips_lost"}', ""),  # a finite double: read (the time checks are the consumer's)
    ('{"t": 1e400, "type": "ips_lost"}', "out of range"),  # beyond a double: not infinity, an error
    ('{"t": 1.0, "type": "wheels", "ticks": [1, 2, 3, 9223372036854775808]}', "`$.ticks[3]`"),
    ('{"t": 1.0, "type": "wheels", "ticks": [1, 2, 3, -9223372036854775809]}', "`$.ticks[3]`"),
    ('{"t": 1.0, "type": "wheels", "ticks": [1, 2, 3.0, 4]}', "Expected `int`, got `float`"),
    ('{"t": 1.0, "type": "wheels", "ticks": [1, 2, 3]}', "`$.ticks`"),
    ('{"t": true, "type": "wheels", "ticks": [1, 2, 3, 4]}', "Expected `float`, got `bool`"),
    ('{"t": "1.0", "type": "ips_lost"}', "Expected `float`, got `str`"),
    ('{"type": "ips", "x": 1.0, "y": 2.0}', "missing required field `t`"),
    ('{"t": 1.0, "type": "truth", "x": 1.0, "y": 2.0, "theta": null}', "got `null`"),
    ('{"t": 1.0, "x": 1.0}', "missing required field `type`"),
    ('{"t": 1.0, "type": 7}', "`$.type`"),
    (GOOD + " trailing", "trailing characters"),
    ('{"t": 1.0, "type": "wheels", "ticks": [1, 2, 3, 4], "extra": ' + "[" * 2000 + "]" * 2000 + "}", "nested too"),
    ('{"type": "meta", "robot": ' + '{"a": ' * 2000 + "1" + "}" * 2001, "nested too deeply"),
    ('{"t": 1.0, "type": "ips_lost"', "truncated"),
]


def test_a_written_log_reads_back_as_its_events_rounded_to_micro_units(tmp_path: Path) -> None:
    text = simulated_text(sim_config((0.1, -0.05)), seed=3)
    written = parse_lines(text.splitlines())
    assert not written.problems
    assert {type(e) for e in written.events} == {Wheels, IpsFix, sensorlog.IpsLost, Truth, sensorlog.Command}
    events = [
        Wheels(0.123456789, (1, -2, 3, 2**62)),
        TwistSample(1.0000004, 0.1, -0.2, 0.0),
        IpsFix(2.5, 1.25, -3.0, 0.3, 2.4000001),
        Truth(3.0, 1.0, 2.0),  # without heading
        Truth(3.1, 1.0, 2.0, -1.5),
        *written.events[:500],
    ]
    buffer = io.StringIO()
    writer = LogWriter(buffer, written.meta)
    for event in events:
        writer.write(event)
    path = tmp_path / "log.jsonl"
    path.write_text(buffer.getvalue(), encoding="utf-8")
    log = read_log(path)
    assert not log.problems
    assert log.meta == written.meta
    assert log.meta.robot["ips_offset"] == [0.1, -0.05]
    assert len(log.events) == len(events)
    for got, expected in zip(log.events, events, strict=True):
        assert type(got) is type(expected)
        if isinstance(got, Truth) and math.isnan(got.theta):
            assert math.isnan(expected.theta)  # type: ignore[union-attr]
        else:
            assert got == rounded(expected)
    assert log.events[0] == Wheels(0.123457, (1, -2, 3, 2**62))
    assert '"theta"' not in buffer.getvalue().splitlines()[4]  # JSON has no NaN: the heading is left out


@pytest.mark.parametrize(("line", "reason"), BAD_LINES)
def test_each_bad_line_is_reported_with_its_number_and_reason_and_the_rest_is_read(line: str, reason: str) -> None:
    lines = [GOOD, "", line, GOOD]
    log = parse_lines(lines)
    if not reason:
        assert not log.problems
        assert len(log.events) == 3
        return
    assert len(log.problems) == 1
    assert log.problems[0].startswith("line 3: ")
    assert reason in log.problems[0]
    assert log.events == [Wheels(0.5, (1, 2, 3, 4))] * 2


def test_unknown_types_are_counted_not_reported_and_optional_fields_take_their_defaults() -> None:
    log = parse_lines(
        [
            '{"t": 1.0, "type": "lidar", "ranges": [1.0, 2.0]}',
            '{"t": 1.1, "type": "lidar"}',
            '{"t": 1.2, "type": "imu", "a": {"x": 1}}',
            '{"t": 1.3, "type": "ips", "x": 1.0, "y": 2.0}',
            '{"t": 1.4, "type": "truth", "x": 1.0, "y": 2.0, "note": "a field this version does not know"}',
            '{"type": "meta", "robot": {"lx": 0.2}, "source": "s", "format": "robotd-log", "version": 2}',
        ]
    )
    assert not log.problems
    assert log.unknown_types == {"lidar": 2, "imu": 1}
    fix, truth = log.events
    assert isinstance(fix, IpsFix)
    assert fix.t == 1.3
    assert (fix.x, fix.y, fix.z) == (1.0, 2.0, 0.0)
    assert not fix.timed
    assert fix.stated_t == 1.3
    assert encode(fix) == '{"type":"ips","t":1.3,"x":1.0,"y":2.0,"z":0.0}'  # written back without one
    assert isinstance(truth, Truth)
    assert math.isnan(truth.theta)
    assert log.meta == Meta({"lx": 0.2}, "s", version=2)


def test_line_ends_of_any_kind_and_invalid_utf8_are_read_line_by_line(tmp_path: Path) -> None:
    path = tmp_path / "log.jsonl"
    path.write_bytes(
        GOOD.encode()
        + b"\r\n\r\n"
        + GOOD.encode()
        + b"\r"
        + b'{"t": 1.0, "type": "cmd", "vx": "\xff"}\n'
        + GOOD.encode()
    )
    log = read_log(path)
    assert log.events == [Wheels(0.5, (1, 2, 3, 4))] * 3
    assert len(log.problems) == 1
    assert log.problems[0].startswith("line 4: ")


def _damaged(line: str, edits: list[tuple[int, str]]) -> str:
    for position, char in edits:
        at = position % (len(line) + 1)
        line = line[:at] + char + line[at + 1 :]
    return line


LINES = [
    GOOD,
    '{"t": 0.061, "type": "ips", "x": 1.2, "y": 0.4, "z": 0.0, "t_meas": 0.04}',
    '{"t": 0.005, "type": "truth", "x": 1.19, "y": 0.41, "theta": 0.02}',
    '{"t": 0.01, "type": "twist", "vx": 0.2, "vy": 0.0, "wz": 0.0}',
    '{"t": 0.061, "type": "ips_lost"}',
    '{"t": 0.02, "type": "cmd", "vx": 0.3, "vy": 0.0, "wz": 0.0}',
    '{"type": "meta", "format": "robotd-log", "version": 1, "robot": {"lx": 0.1}, "source": "é"}',
    '{"t": 1.0, "type": "lidar"}',
]


@settings(max_examples=200, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.sampled_from(LINES),
            st.lists(st.tuples(st.integers(0, 200), st.sampled_from(list('0-.e9, "[]{}x\x00\r\n\xe9'))), max_size=3),
        ),
        max_size=12,
    )
)
def test_any_damage_is_read_or_reported_line_by_line_and_never_raises(lines: list[tuple[str, list]]) -> None:  # type: ignore[type-arg]
    texts = [_damaged(line, edits).replace("\n", " ") for line, edits in lines]
    log = parse_lines(texts)
    numbers = [int(problem.split(":")[0].removeprefix("line ")) for problem in log.problems]
    assert numbers == sorted(set(numbers))
    assert all(texts[n - 1].strip() for n in numbers)
    metas = sum('"meta"' in text for text in texts)
    read = len(log.events) + sum(log.unknown_types.values()) + len(log.problems)
    assert read <= sum(bool(text.strip()) for text in texts) <= read + metas
