"""estimates.jsonl text by numpy: valid JSON lines whose numbers are Python's '%.6f' and '%.8e', checked against
Python's own formatting and exact decimal arithmetic on random, half-way, signed-zero and extreme values."""

from __future__ import annotations

import io
import json
import math
import re
from decimal import Decimal
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robotd import estimates_file
from robotd.estimates_file import FIXED_LIMIT, format_estimates, write_estimates

FloatArray = npt.NDArray[np.float64]
NUMBER = re.compile(r"-?\d+\.\d+(?:e[-+]\d+)?")
KEYS = ["t", "x", "y", "theta", "cov"]
EXACT_COV = (1e-14, 1e31)  # the magnitudes whose power of ten is exact: '%.8e' byte for byte


def columns(rng: np.random.Generator, n: int) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Random estimates across magnitudes: signs, zeros, -0.0, a symmetric covariance with negative off-diagonals."""

    def fixed(top: float) -> FloatArray:
        values = rng.choice([-1.0, 1.0], n) * 10.0 ** rng.uniform(-9.0, top, n)
        values[rng.random(n) < 0.05] = 0.0
        values[rng.random(n) < 0.05] = -0.0
        return values

    upper = rng.choice([-1.0, 1.0], (n, 6)) * 10.0 ** rng.uniform(-13.9, 30.9, (n, 6))
    upper[:, [0, 3, 5]] = np.abs(upper[:, [0, 3, 5]])
    upper[rng.random((n, 6)) < 0.05] = 0.0
    return fixed(8.9), fixed(5.9), fixed(5.9), fixed(0.5), upper[:, [0, 1, 2, 1, 3, 4, 2, 4, 5]]


def tokens(text: bytes) -> list[list[str]]:
    """Each line's numbers as written: t, x, y, theta, then the nine covariance entries."""
    return [NUMBER.findall(line) for line in text.decode("ascii").splitlines()]


def python_tokens(t: FloatArray, x: FloatArray, y: FloatArray, theta: FloatArray, cov: FloatArray) -> list[list[str]]:
    """The same numbers formatted by Python, one value at a time ('{:.6f}' and '{:.8e}' are '%.6f' and '%.8e')."""
    return [
        [f"{value:.6f}" for value in (t[i], x[i], y[i], theta[i])] + [f"{value:.8e}" for value in cov[i]]
        for i in range(len(t))
    ]


def last_digit_units(token: str, value: float) -> Decimal:
    """|written - value| in units of the written number's last digit, in exact decimal arithmetic."""
    exponent = int(token.split("e")[1]) if "e" in token else 0
    decimals = len(token.split("e", maxsplit=1)[0].split(".")[1])
    return abs(Decimal(token) - Decimal(value)) / Decimal(10) ** (exponent - decimals)


def test_every_line_is_json_with_the_keys_in_order_and_the_numbers_given() -> None:
    t, x, y, theta, cov = columns(np.random.default_rng(1), 300)
    lines = format_estimates(t, x, y, theta, cov).decode("ascii").splitlines(keepends=True)
    assert len(lines) == 300
    for i, line in enumerate(lines):
        assert line.endswith("}\n")
        estimate = json.loads(line)
        assert list(estimate) == KEYS
        for name, values in zip(KEYS, (t, x, y, theta), strict=False):
            assert abs(estimate[name] - values[i]) <= 0.5e-6 + 1e-16 * abs(values[i]), (i, name)
        assert len(estimate["cov"]) == 9
        for written, value in zip(estimate["cov"], cov[i], strict=True):
            assert abs(written - value) <= 5.000001e-9 * abs(value), (i, value)  # half a unit of the ninth digit


def test_numbers_are_pythons_percent_formatting_byte_for_byte() -> None:
    rng = np.random.default_rng(2)
    t, x, y, theta, cov = columns(rng, 2000)
    assert tokens(format_estimates(t, x, y, theta, cov)) == python_tokens(t, x, y, theta, cov)
    general = rng.normal(0.0, 1.0, (2000, 9)) * 10.0 ** rng.uniform(-13.9, 30.9, (2000, 9))  # not symmetric
    assert tokens(format_estimates(t, x, y, theta, general)) == python_tokens(t, x, y, theta, general)


def test_values_next_to_a_rounding_half_way_point_round_as_python() -> None:
    """Decimal halves: most do not exist in binary, so the float is a hair above or below and must round that way."""
    rng = np.random.default_rng(3)
    n = 4000
    whole = np.floor(10.0 ** rng.uniform(0.0, 8.9, n)) * (rng.random(n) < 0.7)
    fixed = (whole + (rng.integers(0, 10**6, n) + 0.5) / 1e6) * rng.choice([-1.0, 1.0], n)
    mantissa = rng.integers(10**8, 10**9, (n, 9)) + 0.5
    cov = mantissa * 10.0 ** rng.integers(-22, 22, (n, 9)).astype(np.float64)  # from 1e-14 to 1e30
    cov += rng.integers(-3, 4, (n, 9)) * np.spacing(cov)  # and a few binary steps either side
    exact_ties = np.array([0.0078125, 0.0234375, -0.5, 2.5])  # k/128: '%.6f' of the exact half rounds to even
    fixed[: exact_ties.size] = exact_ties
    cov[0, :4] = [100000000.5, 100000001.5, 2.5, -0.0078125]  # exact halves of a nine-digit mantissa
    columns_ = (fixed, fixed[::-1].copy(), -fixed, fixed / 10.0, cov)
    written = tokens(format_estimates(*columns_))
    assert written == python_tokens(*columns_)
    assert [row[0] for row in written[:4]] == ["0.007812", "0.023438", "-0.500000", "2.500000"]
    assert written[0][4:8] == ["1.00000000e+08", "1.00000002e+08", "2.50000000e+00", "-7.81250000e-03"]


def test_rounding_carries_across_a_power_of_ten() -> None:
    carried = np.array([9.9999999996, -9.9999999996, 0.9999996, 99999.9999996])
    cov = np.tile([9.9999999996e-05, -9.9999999996e-05, 9.999999999e8, 9.9999999996e30, 0.0, 1.0, 1e-99, 0, 0], (4, 1))
    cov[:, 6] = 9.999999996e-100  # rounds up to 1.00000000e-99: two exponent digits, though the value is below 1e-99
    written = tokens(format_estimates(carried, carried, carried, carried, cov))
    assert [row[0] for row in written] == ["10.000000", "-10.000000", "1.000000", "100000.000000"]
    assert written[0][4:8] == ["1.00000000e-04", "-1.00000000e-04", "1.00000000e+09", "1.00000000e+31"]
    assert written[0][10] == "1.00000000e-99"
    assert written == python_tokens(carried, carried, carried, carried, cov)


def test_powers_of_ten_and_their_neighbours_take_the_right_exponent() -> None:
    """Beside a power of ten the exponent's estimate (from log10) and the rounding disagree most easily."""
    powers = 10.0 ** np.arange(-307, 308)
    cov = np.column_stack([np.nextafter(powers, 0.0), powers, np.nextafter(powers, np.inf)] * 3)
    zeros = np.zeros(len(powers))
    written = tokens(format_estimates(zeros, zeros, zeros, zeros, cov))
    python = python_tokens(zeros, zeros, zeros, zeros, cov)
    for written_row, python_row, values in zip(written, python, cov, strict=True):
        for token, expected, value in zip(written_row[4:], python_row[4:], values, strict=True):
            assert token.split("e")[1] == expected.split("e")[1], (token, expected)
            assert last_digit_units(token, value) <= Decimal("0.500001"), (token, value)


def test_the_largest_and_smallest_magnitudes() -> None:
    t = np.array([999999999.999999, -999999999.999999, FIXED_LIMIT - 1.0, 0.0])
    x = np.array([999999.9999994, -999999.9999996, 1e-300, -5e-324])
    extremes = [1.7976931348623157e308, -5e-324, 1e-100, 2.2250738585072014e-308, 1e300, -1e-15, 1e31, 3e-14, 1e-5]
    cov = np.tile(extremes, (4, 1))
    text = format_estimates(t, x, x, x, cov)
    written = tokens(text)
    assert [row[0] for row in written] == [
        "999999999.999999",
        "-999999999.999999",
        "999999999999999.000000",
        "0.000000",
    ]
    assert [row[1] for row in written] == ["999999.999999", "-1000000.000000", "0.000000", "-0.000000"]
    assert written == python_tokens(t, x, x, x, cov)  # these extremes are not near a half-way point
    for line in text.decode().splitlines():
        assert json.loads(line)["cov"][0] == pytest.approx(1.7976931348623157e308, rel=1e-8)


def test_far_covariances_lie_within_half_a_last_digit_unit_or_one_digit_from_python() -> None:
    """Below 1e-14 and from 1e31 up the scaling rounds more than once: the last digit may be one off at a half."""
    rng = np.random.default_rng(4)
    n = 2000
    exponents = np.where(rng.random((n, 9)) < 0.5, rng.uniform(-323.0, -14.1, (n, 9)), rng.uniform(31.0, 307.9, (n, 9)))
    cov = rng.choice([-1.0, 1.0], (n, 9)) * 10.0**exponents
    zeros = np.zeros(n)
    written = tokens(format_estimates(zeros, zeros, zeros, zeros, cov))
    python = python_tokens(zeros, zeros, zeros, zeros, cov)
    for i in range(n):
        for token, expected, value in zip(written[i][4:], python[i][4:], cov[i], strict=True):
            assert last_digit_units(token, value) <= Decimal("0.500001"), (token, value)
            if token != expected:  # then one unit apart, around a value within a hair of the half-way point
                assert abs(Decimal(token) - Decimal(expected)) == Decimal(10) ** (int(token.split("e")[1]) - 8)
                assert abs(last_digit_units(expected, value) - Decimal("0.5")) < Decimal("1e-6")


def test_negative_zero_and_negatives_rounding_to_zero_keep_their_sign() -> None:
    signed = np.array([-0.0, -1e-7, 0.0, 4e-7])
    cov = np.tile([-0.0, 0.0, -1e-300, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0], (4, 1))
    text = format_estimates(signed, signed, signed, signed, cov)
    written = tokens(text)
    assert [row[0] for row in written] == ["-0.000000", "-0.000000", "0.000000", "0.000000"]
    assert written[0][4:7] == ["-0.00000000e+00", "0.00000000e+00", "-1.00000000e-300"]
    first = json.loads(text.decode().splitlines()[0])
    assert math.copysign(1.0, first["t"]) == -1.0
    assert math.copysign(1.0, first["cov"][0]) == -1.0
    only_negative_zero = np.abs(cov)
    only_negative_zero[1, 8] = -0.0  # the one sign in the covariance
    assert tokens(format_estimates(signed, signed, signed, signed, only_negative_zero))[1][12] == "-0.00000000e+00"


def test_no_lines_and_one_line() -> None:
    empty = np.zeros(0)
    assert format_estimates(empty, empty, empty, empty, np.zeros((0, 9))) == b""
    stream = io.BytesIO()
    assert write_estimates(stream, empty, empty, empty, empty, np.zeros((0, 9))) == 0
    assert stream.getvalue() == b""
    one = np.array([12.34])
    text = format_estimates(one, -one, one, one, np.eye(3).reshape(1, 9))
    assert text.count(b"\n") == 1
    assert text.endswith(b"]}\n")
    assert json.loads(text) == {"t": 12.34, "x": -12.34, "y": 12.34, "theta": 12.34, "cov": [1, 0, 0, 0, 1, 0, 0, 0, 1]}


def test_line_layout_is_the_same_on_every_line_with_numbers_right_aligned() -> None:
    t, x, y, theta, cov = columns(np.random.default_rng(5), 200)
    lines = format_estimates(t, x, y, theta, cov).decode("ascii").splitlines()
    fixed = r" *-?(?:0|[1-9]\d*)\.\d{6}"
    entry = r" *-?\d\.\d{8}e[-+]\d{2,3} *"
    pattern = re.compile(
        rf'\{{"t": {fixed}, "x": {fixed}, "y": {fixed}, "theta": {fixed}, "cov": \[{entry}(?:, {entry}){{8}}\]\}}'
    )
    for line in lines:
        assert pattern.fullmatch(line), line
    assert len({len(line) for line in lines}) == 1
    for key in ('"x"', '"y"', '"theta"', '"cov"', ", "):
        assert len({line.index(key) for line in lines}) == 1
    assert len({line.index(".") for line in lines}) == 1  # t's decimal points line up
    assert all("+" not in re.sub(r"e[-+]\d+", "", line) for line in lines)  # only exponents carry a plus sign


def test_chunks_join_seamlessly_and_the_stream_writer_writes_the_same_text(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    t, x, y, theta, cov = columns(np.random.default_rng(6), 50)
    whole = format_estimates(t, x, y, theta, cov)
    monkeypatch.setattr(estimates_file, "CHUNK_LINES", 7)
    assert format_estimates(t, x, y, theta, cov) == whole
    assert format_estimates(list(t), list(x), list(y), list(theta), cov.tolist()) == whole  # replay's tracks are lists
    path = tmp_path / "estimates.jsonl"
    with path.open("wb") as stream:
        assert write_estimates(stream, t, x, y, theta, cov) == len(whole)
    assert path.read_bytes() == whole


@pytest.mark.parametrize(
    ("field", "line", "bad", "message"),
    [
        ("t", 3, math.nan, "estimate line 3: t = nan"),
        ("theta", 0, -math.inf, "estimate line 0: theta = -inf"),
        ("x", 5, FIXED_LIMIT, "estimate line 5: x = 1000000000000000.0"),
        ("cov", 2, math.inf, "estimate line 2: cov[4] = inf"),
        ("cov", 4, math.nan, "estimate line 4: cov[4] = nan"),
    ],
)
def test_unwritable_numbers_raise_naming_line_and_field_and_write_nothing(
    field: str, line: int, bad: float, message: str, tmp_path: Path
) -> None:
    t, x, y, theta, cov = columns(np.random.default_rng(7), 6)
    values = dict(zip(KEYS, (t, x, y, theta, cov), strict=True))
    if field == "cov":
        cov[line, 4] = bad
    else:
        values[field][line] = bad
    with pytest.raises(ValueError, match=re.escape(message)):
        format_estimates(t, x, y, theta, cov)
    path = tmp_path / "estimates.jsonl"
    with path.open("wb") as stream, pytest.raises(ValueError, match=re.escape(message)):
        write_estimates(stream, t, x, y, theta, cov)
    assert path.read_bytes() == b""


def test_shapes_are_checked() -> None:
    ok = np.zeros(3)
    with pytest.raises(ValueError, match=r"x has shape \(2,\), expected \(3,\)"):
        format_estimates(ok, np.zeros(2), ok, ok, np.zeros((3, 9)))
    with pytest.raises(ValueError, match=r"cov has shape \(3, 6\), expected \(3, 9\)"):
        format_estimates(ok, ok, ok, ok, np.zeros((3, 6)))
    with pytest.raises(ValueError, match="t must be one-dimensional"):
        format_estimates(np.zeros((3, 1)), ok, ok, ok, np.zeros((3, 9)))


finite = st.floats(allow_nan=False, allow_infinity=False)


@settings(max_examples=150, deadline=None)
@given(
    st.lists(
        st.tuples(st.floats(-1e6, 1e6), st.floats(-1e9, 1e9), st.lists(finite, min_size=9, max_size=9)), max_size=8
    )
)
def test_any_finite_numbers_are_written_as_python_writes_them(
    rows: list[tuple[float, float, list[float]]],
) -> None:
    position = np.array([row[0] for row in rows])
    t = np.array([row[1] for row in rows])
    cov = np.array([row[2] for row in rows]).reshape(len(rows), 9)
    written = tokens(format_estimates(t, position, -position, position, cov))
    python = python_tokens(t, position, -position, position, cov)
    assert [row[:4] for row in written] == [row[:4] for row in python]
    for tokens_row, python_row, values in zip(written, python, cov, strict=True):
        for token, expected, value in zip(tokens_row[4:], python_row[4:], values, strict=True):
            if value == 0 or EXACT_COV[0] <= abs(value) < EXACT_COV[1]:
                assert token == expected
            else:
                assert last_digit_units(token, value) <= Decimal("0.500001"), (token, value)
