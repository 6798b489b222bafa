"""Reading a sensor log gives exactly what reading it line by line through json.loads gives: the bytes-level bulk
reader (robotd.logbulk) for the standard lines, the per-line reader for the rest, and read_log's own file handling
(UTF-8 with errors replaced, universal newlines)."""

from __future__ import annotations

import io
import json
import random
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from log_reference import reference_lines

from robotd import logbulk, logfile, synthlog
from robotd.logfile import LogWriter, SensorLog, Truth, Wheels

WHEELS_LINE = '{{"t": {}, "type": "wheels", "ticks": [{}, {}, {}, {}]}}'
TRUTH_LINE = '{{"t": {}, "type": "truth", "x": {}, "y": {}, "theta": {}}}'
IPS_LINE = '{{"t": {}, "type": "ips", "x": {}, "y": {}, "z": {}, "t_meas": {}}}'
TWIST_LINE = '{{"t": {}, "type": "twist", "vx": {}, "vy": {}, "wz": {}}}'
TEMPLATES = [(WHEELS_LINE, 5), (TRUTH_LINE, 4), (IPS_LINE, 5), (TWIST_LINE, 4)]

# number places that look almost like the writer's: each must read as json.loads reads it, or go to the per-line reader
ODD_NUMBERS = [
    *("0", "-0", "0.0", "-0.0", "7", "-7", "10", "100.5", "0.000001", "-0.5", "9007199254740993"),
    *("01", "-01", "00", "00.5", ".5", "-.5", "5.", "-", "", "--1", "+1", "1-2", "1..2", "1.2.3", "1.-2"),
    *("1e5", "1E-7", "1.5e3", "NaN", "Infinity", "-Infinity", "1_0", " 1", "1 ", "１", "1\u00a0"),
    *("1234567890123456", "12345678901234567", "123456789012345.6", "12345678901234.56", "-123456789012345"),
    *("0.12345678", "0.1234567", "-1234567.1234567", "99999999", "999999999", "-99999999", "-999999999"),
    *("9223372036854775807", "9223372036854775808", "-9223372036854775809", "1" * 40),
]


def _reference_file(path: Path) -> SensorLog:
    """The file read as a text file is (UTF-8, errors replaced, universal newlines), then line by line."""
    with open(path, encoding="utf-8", errors="replace") as stream:
        text = stream.read()
    lines = [line + "\n" for line in text.split("\n")]
    lines[-1] = lines[-1].removesuffix("\n")
    return reference_lines(lines if lines[-1] else lines[:-1])


def _key(value: object) -> object:
    # floats by their bits: NaN equals NaN, and -0.0 differs from 0.0
    return struct.pack("<d", value) if isinstance(value, float) else value


def _assert_same(parsed: SensorLog, reference: SensorLog) -> None:
    def events(log: SensorLog) -> list[tuple[object, ...]]:
        return [(type(e), *(_key(getattr(e, name)) for name in e.__slots__)) for e in log.events]

    assert parsed.problems == reference.problems
    assert parsed.unknown_types == reference.unknown_types
    assert parsed.meta == reference.meta
    assert events(parsed) == events(reference)
    columns, expected = parsed.columns(), logfile.Columns.from_events(reference.events)
    assert columns.kinds.tobytes() == expected.kinds.tobytes()
    assert columns.wheels_t.tobytes() == expected.wheels_t.tobytes()
    assert columns.wheels_ticks.dtype == np.int64
    assert columns.wheels_ticks.tobytes() == expected.wheels_ticks.tobytes()
    assert columns.truth.tobytes() == expected.truth.tobytes()


def _canonical_text(seed: int) -> str:
    meta, events = synthlog.generate(synthlog.SynthSpec(loops=1, side_m=0.5, ips_offset_m=(0.1, -0.05)), seed)
    buffer = io.StringIO()
    writer = LogWriter(buffer, meta)
    for event in events:
        writer.write(event)
    events_with_truth = [Truth(0.001 * i, 1e-5 * i, -0.25 * i, -1e-7 * i) for i in range(30)]  # exponents too
    for event in events_with_truth:
        writer.write(event)
    return buffer.getvalue()


def test_a_writers_log_is_read_in_bulk_but_for_its_meta_and_exponents(tmp_path: Path) -> None:
    text = _canonical_text(3)
    kinds = logbulk.parse_standard(text.encode()).kinds
    lines = text.splitlines()
    per_line = [line for line, kind in zip(lines, kinds.tolist(), strict=True) if kind == logbulk.PER_LINE]
    assert all('"meta"' in line or '"ips_lost"' in line or "e-" in line for line in per_line)
    assert sum('"wheels"' in line for line in per_line) == 0
    assert len(per_line) < len(lines) // 20
    path = tmp_path / "log.jsonl"
    path.write_text(text, encoding="utf-8")
    _assert_same(logfile.read_log(path), _reference_file(path))


def test_numbers_read_in_bulk_are_the_doubles_and_integers_json_reads() -> None:
    rng = np.random.default_rng(5)
    count = 4000
    # decimals of 1 to 14 digits with 0 to 7 of them after the point, signed; integers of up to 15 digits
    digits = rng.integers(1, 15, count)  # with its "-" and ".", a place of at most 16 bytes
    fraction = np.minimum(rng.integers(0, 8, count), digits - 1)
    mantissas = [int(rng.integers(0, 10 ** int(d))) for d in digits]
    times = []
    for mantissa, places, negative in zip(mantissas, fraction.tolist(), rng.random(count) < 0.4, strict=True):
        whole, part = divmod(mantissa, 10**places)
        token = f"{whole}.{part:0{places}d}" if places else str(whole)
        times.append(("-" if negative else "") + token)
    ticks = [str(int(rng.integers(-(10**15), 10**15)) // 10 ** int(rng.integers(0, 15))) for _ in range(4 * count)]
    text = "".join(WHEELS_LINE.format(t, *ticks[4 * i : 4 * i + 4]) + "\n" for i, t in enumerate(times))
    bulk = logbulk.parse_standard(text.encode())
    assert (bulk.kinds == logbulk.WHEELS_KIND).all()
    assert bulk.wheels_t.tobytes() == np.array([float(json.loads(t)) for t in times]).tobytes()
    assert bulk.wheels_ticks.ravel().tolist() == [json.loads(tick) for tick in ticks]


@pytest.mark.parametrize("odd", ODD_NUMBERS)
@pytest.mark.parametrize(("template", "places"), TEMPLATES)
def test_each_odd_number_in_each_place_is_read_as_json_would(template: str, places: int, odd: str) -> None:
    lines = []
    for place in range(places):
        numbers = ["1.5", "-2", "30", "0.25", "7"][:places]
        numbers[place] = odd
        lines.append(template.format(*numbers) + "\n")
    mixed = [lines[0], WHEELS_LINE.format(0.5, 1, 2, 3, 4) + "\n", *lines[1:]]
    _assert_same(logfile.parse_lines(mixed), reference_lines(mixed))


@pytest.mark.parametrize(("template", "places"), TEMPLATES)
def test_a_line_damaged_at_any_one_byte_is_read_as_json_would(template: str, places: int) -> None:
    line = template.format(*["1.5", "-2", "30", "0.25", "7"][:places])
    damaged = [line[:at] + char + line[at + 1 :] for at in range(len(line)) for char in ("x", "7", " ", "")]
    damaged += [line[:at] + "," + line[at:] for at in range(len(line) + 1)]  # a comma more: the commas move
    lines = [text + "\n" for text in damaged]
    parsed = logfile.parse_lines(lines)
    _assert_same(parsed, reference_lines(lines))
    assert len(parsed.problems) > len(lines) // 2


def test_a_last_line_without_newline_is_reported_as_json_reports_it(tmp_path: Path) -> None:
    path = tmp_path / "log.jsonl"
    path.write_text(WHEELS_LINE.format(1, 2, 3, 4, 5) + '\n{"t": 1.5, "type": ', encoding="utf-8")
    log = logfile.read_log(path)
    _assert_same(log, _reference_file(path))
    assert log.problems == ["line 2: Expecting value: line 1 column 20 (char 19)"]


def _number() -> st.SearchStrategy[str]:
    return st.one_of(
        st.sampled_from(ODD_NUMBERS),
        st.floats(allow_nan=False, allow_infinity=False).map(lambda x: json.dumps(round(x, 6))),
        st.integers(-(10**17), 10**17).map(str),
        st.text(alphabet="0123456789.-+eE", max_size=18),
    )


def _line() -> st.SearchStrategy[str]:
    standard = st.sampled_from(TEMPLATES).flatmap(
        lambda shape: st.lists(_number(), min_size=shape[1], max_size=shape[1]).map(
            lambda numbers: shape[0].format(*numbers)
        )
    )
    other = st.sampled_from(
        [
            "",
            "   ",
            '{"type": "meta", "format": "robotd-log", "version": 1, "robot": {}, "source": "é"}',
            '{"t": 1.0, "type": "ips_lost"}',
            '{"t": 1.0, "type": "twist", "vx": 0.1, "vy": 0, "wz": -0.0}',
            '{"t": 1.0, "type": "lidar"}',
            '{"t": 1.0, "type": "wheels", "ticks": [1, 2, 3, 4], "t": 2.0}',
            "[1, 2]",
            "{not json",
        ]
    )
    return st.one_of(standard, standard, other)


def _damaged(line: str, edits: list[tuple[int, str]]) -> str:
    for position, char in edits:
        at = position % (len(line) + 1)
        line = line[:at] + char + line[at + 1 :]
    return line


@settings(max_examples=150, deadline=None)
@given(
    lines=st.lists(
        st.tuples(
            _line(),
            st.lists(st.tuples(st.integers(0, 200), st.sampled_from(list('0-.e, "[]{}x\x00\r\xe9'))), max_size=2),
        ),
        max_size=12,
    ),
    newline=st.sampled_from(["\n", "\r\n", "\r"]),
    final_newline=st.booleans(),
    junk=st.binary(max_size=3),
)
def test_any_log_is_read_as_a_text_file_read_line_by_line_through_json_would_be(
    tmp_path_factory: pytest.TempPathFactory,
    lines: list[tuple[str, list[tuple[int, str]]]],
    newline: str,
    final_newline: bool,
    junk: bytes,
) -> None:
    texts = [_damaged(line, edits) if edits else line for line, edits in lines]
    data = newline.join(texts).encode("utf-8", "surrogatepass") + (newline.encode() if final_newline else b"")
    data += junk  # bytes that may not be UTF-8, or may end a line
    path = tmp_path_factory.mktemp("log") / "log.jsonl"
    path.write_bytes(data)
    _assert_same(logfile.read_log(path), _reference_file(path))
    given_lines = [text + "\n" for text in texts]
    _assert_same(logfile.parse_lines(given_lines), reference_lines(given_lines))


def test_a_log_is_read_the_same_across_block_boundaries(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    lines = _canonical_text(4).splitlines(keepends=True)
    rng = random.Random(6)
    for odd in ODD_NUMBERS:  # odd lines here and there, some at the blocks' edges
        lines.insert(rng.randrange(len(lines)), WHEELS_LINE.format(odd, 1, 2, 3, 4) + "\n")
    path = tmp_path / "log.jsonl"
    path.write_text("".join(lines).rstrip("\n"), encoding="utf-8")
    reference = _reference_file(path)
    for block in (1, 37, 512, 4096):
        monkeypatch.setattr(logbulk, "BLOCK", block)
        _assert_same(logfile.read_log(path), reference)


def test_crlf_line_ends_and_a_missing_final_newline_still_take_the_bulk_path(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    text = _canonical_text(7) + WHEELS_LINE.format(99.5, -1, 2, -3, 4)
    path = tmp_path / "log.jsonl"
    path.write_bytes(text.replace("\n", "\r\n").encode())
    seen: list[logbulk.Bulk] = []
    parse_standard = logbulk.parse_standard

    def spy(data: bytes) -> logbulk.Bulk:
        seen.append(parse_standard(data))
        return seen[-1]

    monkeypatch.setattr(logbulk, "parse_standard", spy)
    log = logfile.read_log(path)
    _assert_same(log, _reference_file(path))
    assert not log.problems
    assert log.events[-1] == Wheels(99.5, (-1, 2, -3, 4))
    (bulk,) = seen
    assert len(bulk.wheels_t) == text.count('"wheels"')  # every wheels line, the last one too, read in bulk


def test_lines_given_with_newlines_or_surrogates_inside_are_read_one_by_one() -> None:
    standard = WHEELS_LINE.format(1.5, 1, 2, 3, 4)
    lines = [standard, standard.replace(", ", ",\n", 1), standard + "\n", "\ud800" + standard, standard[:-1] + "\n"]
    parsed = logfile.parse_lines(lines)
    _assert_same(parsed, reference_lines(lines))
    assert len(parsed.events) == 3  # the one split by a newline is still one line, and JSON's whitespace
    assert [int(problem.split(":")[0].split()[1]) for problem in parsed.problems] == [4, 5]
