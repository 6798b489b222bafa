"""The text of `robotd replay`'s estimates.jsonl, formatted by numpy array arithmetic instead of Python's % operator.

A line: `{"t":    0.050000, "x":   -0.350000, ..., "cov": [ 1.00000000e-04, -2.00000000e-06, ...]}`. format_estimates
returns the text; write_estimates writes it to a binary stream a chunk at a time, never holding it all.

Theory of operation: every line has one layout, each number right-aligned in a field as wide as its column needs
(spaces between JSON tokens are insignificant: integer parts take whole four-byte words, and when some covariance
entry needs a three-digit exponent the others are followed by a space), known beforehand from the columns' extreme
values because rounding is monotonic. A fixed-point value is split into its integer part and its fraction (both
exact in binary), the fraction scaled by 1e6 and rounded to an integer; a covariance entry is scaled by a power of ten
to a nine-digit integer mantissa and a decimal exponent. Their digits, four at a time, come from integer division of
whole columns and are looked up as ready-made ASCII words ("0000" to "9999", "  12", " -12": four bytes read as one
uint32), stored straight into a (lines x bytes) array that already holds the template's constant bytes; that array's
bytes are the text. Lines are done a few thousand at a time so that the temporaries stay in the processor's cache; no
Python step runs per line or per number.

Rounding is Python's (correct rounding of the exact binary value, ties to even): a scaled value is rounded after a
single floating-point rounding, and where that lands exactly on a half, the sign of the exact product's error
(Dekker's two-product) decides. So the numbers are byte for byte those of '%.6f' and '%.8e', except a covariance entry
below 1e-14 or from 1e31 up, whose power of ten is not exact in binary: its last digit may differ from '%.8e' by one
when it lies within about 1e-6 of a last-digit unit of a half-way point.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from typing import BinaryIO

import numpy as np
import numpy.typing as npt

ArrayLike = npt.ArrayLike
FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
ByteArray = npt.NDArray[np.uint8]
WordArray = npt.NDArray[np.uint16] | npt.NDArray[np.uint32]

FIXED_FIELDS = ("t", "x", "y", "theta")
FIXED_DECIMALS = 6  # t, x, y, theta as '%.6f'
COV_ENTRIES = 9  # the 3x3 covariance, row-major, each entry as '%.8e' (nine significant digits)
FIXED_LIMIT = 1e15  # past this a fixed-point value has more digits than binary64 carries
CHUNK_LINES = 4096  # lines formatted together: their temporaries stay in the processor's cache

_SPACE, _MINUS, _ZERO = b" -0"
_SYMMETRIC = [0, 1, 2, 1, 3, 4, 2, 4, 5]  # the nine entries' columns among the upper triangle's six
_EXACT_POWERS = 22  # 10**k is exact in binary64 for 0 <= k <= 22 (5**22 < 2**53)
_POW10 = np.array([10.0**k for k in range(_EXACT_POWERS + 1)])
_SPLITTER = 134217729.0  # 2**27 + 1: Veltkamp's split of a binary64 into two halves of at most 26 bits
_EXPONENT_RANGE = 400  # binary64's decimal exponents lie in (-400, 400)
_GROUP = 10**4  # digits go four to a word

# ready-made words: one gather and one store per four digits instead of arithmetic per digit
_DIGIT_TEXT = (np.arange(_GROUP)[:, None] // 10 ** np.arange(3, -1, -1) % 10 + _ZERO).astype(np.uint8)  # "0042"
_FOUR_DIGITS = _DIGIT_TEXT.view(np.uint32).ravel()
_TWO_DIGITS = np.ascontiguousarray(_DIGIT_TEXT[:100, 2:]).view(np.uint16).ravel()  # "00" to "99"
_LEAD_DIGIT = np.frombuffer(b"".join(b"%d." % k for k in range(10)), dtype=np.uint16).copy()  # "4." (first digit)
_EXPONENT_TEXT = np.frombuffer(  # "e-05 ", "e+123": the exponent of e + _EXPONENT_RANGE, padded right to five bytes
    b"".join((b"e%+03d" % e).ljust(5) for e in range(-_EXPONENT_RANGE, _EXPONENT_RANGE)),
    dtype=np.uint8,
).reshape(-1, 5)
_EXPONENT_WORD = np.ascontiguousarray(_EXPONENT_TEXT[:, :4]).view(np.uint32).ravel()


def _integer_words() -> npt.NDArray[np.uint32]:
    """Words of a right-aligned signed integer, four digits each, indexed by kind * 10**4 + the group's value.

    Kinds: 0 zero-padded ("0042", a group with digits on its left); 1 leading ("  42"); 2 leading, negative (" -42",
    or "1234" whose minus goes in the word on its left); then blank ("    ", left of the number: index 30000) and
    blank with that minus ("   -": 30001).
    """
    digits = 1 + (np.arange(_GROUP)[:, None] >= [10, 100, 1000]).sum(axis=1)
    leading = np.where(np.arange(4) < 4 - digits[:, None], _SPACE, _DIGIT_TEXT).astype(np.uint8)
    negative = leading.copy()
    short = np.flatnonzero(digits < 4)
    negative[short, 3 - digits[short]] = _MINUS
    blank = np.frombuffer(b"       -", dtype=np.uint8).reshape(2, 4)
    return np.concatenate([_DIGIT_TEXT, leading, negative, blank]).view(np.uint32).ravel()


_INTEGER_WORDS = _integer_words()
_LEADING, _BLANK = _GROUP, 3 * _GROUP  # leading negative at _LEADING + _GROUP, blank with a minus at _BLANK + 1


def format_estimates(t: ArrayLike, x: ArrayLike, y: ArrayLike, theta: ArrayLike, cov: ArrayLike) -> bytes:
    """n estimates.jsonl lines, `{"t": <t>, "x": <x>, "y": <y>, "theta": <theta>, "cov": [<c0>, ..., <c8>]}`, as bytes.

    t, x, y, theta: n floats each (arrays or sequences), written as '%.6f' writes them; a negative value keeps its
    sign even when it rounds to zero, -0.0 included ("-0.000000"). cov: n x 9 (3x3 row-major), each entry written
    as '%.8e' writes it ("-0.00000000e+00" for -0.0). Numbers are right-aligned in columns, the same on every line.
    Raises ValueError, naming the line and field, for a non-finite number or a fixed-point magnitude >= FIXED_LIMIT.
    """
    fixed, cov_rows = _checked(t, x, y, theta, cov)
    if not len(cov_rows):
        return b""
    layout = _Layout.of(fixed, cov_rows)
    lines = np.empty((len(cov_rows), layout.template.size), dtype=np.uint8)
    for rows in _chunks(len(cov_rows)):
        layout.fill(lines[rows], [values[rows] for values in fixed], cov_rows[rows])
    return lines.tobytes()


def write_estimates(  # noqa: PLR0917 - the stream, then the same five columns as format_estimates
    stream: BinaryIO, t: ArrayLike, x: ArrayLike, y: ArrayLike, theta: ArrayLike, cov: ArrayLike
) -> int:
    """Write format_estimates' text to a binary stream a chunk at a time (never the whole text in memory); its size.

    Everything is checked before the first byte is written: a ValueError leaves the stream untouched.
    """
    fixed, cov_rows = _checked(t, x, y, theta, cov)
    if not len(cov_rows):
        return 0
    layout = _Layout.of(fixed, cov_rows)
    buffer = np.empty((min(len(cov_rows), CHUNK_LINES), layout.template.size), dtype=np.uint8)
    for rows in _chunks(len(cov_rows)):
        lines = buffer[: rows.stop - rows.start]
        layout.fill(lines, [values[rows] for values in fixed], cov_rows[rows])
        stream.write(lines.data)
    return len(cov_rows) * layout.template.size


def _chunks(n: int) -> Iterator[slice]:
    """Consecutive slices of at most CHUNK_LINES lines covering n lines."""
    for first in range(0, n, CHUNK_LINES):
        yield slice(first, min(first + CHUNK_LINES, n))


def _checked(
    t: ArrayLike, x: ArrayLike, y: ArrayLike, theta: ArrayLike, cov: ArrayLike
) -> tuple[list[FloatArray], FloatArray]:
    """The inputs as float64 arrays, four of n and one n x 9; else ValueError naming the first line and field that
    cannot be written (wrong shape, not finite, a fixed-point magnitude >= FIXED_LIMIT)."""
    if np.ndim(t) != 1:
        raise ValueError(f"estimates: t must be one-dimensional, not of shape {np.shape(t)}")
    n = np.shape(t)[0]
    for name, values in zip(FIXED_FIELDS, (t, x, y, theta), strict=True):
        if np.shape(values) != (n,):
            raise ValueError(f"estimates: {name} has shape {np.shape(values)}, expected ({n},) like t")
    if np.shape(cov) != (n, COV_ENTRIES):
        raise ValueError(f"estimates: cov has shape {np.shape(cov)}, expected ({n}, {COV_ENTRIES})")
    fixed = [np.asarray(values, dtype=np.float64) for values in (t, x, y, theta)]
    cov_rows = np.asarray(cov, dtype=np.float64)
    if not n:
        return fixed, cov_rows
    for name, values in zip(FIXED_FIELDS, fixed, strict=True):
        if not _biggest(values) < FIXED_LIMIT:  # NaN fails every comparison
            line = int(np.argmin(np.abs(values) < FIXED_LIMIT))
            raise ValueError(f"estimate line {line}: {name} = {float(values[line])!r} cannot be written {_WHY}")
    if not np.isfinite(_biggest(cov_rows)):
        line, entry = np.argwhere(~np.isfinite(cov_rows))[0]
        raise ValueError(
            f"estimate line {line}: cov[{entry}] = {float(cov_rows[line, entry])!r} cannot be written {_WHY}"
        )
    return fixed, cov_rows


_WHY = f"(every number must be finite, and t, x, y, theta below {FIXED_LIMIT:g} in magnitude)"


def _biggest(values: FloatArray) -> float:
    """The largest magnitude among values, NaN if there is one (without an array of magnitudes)."""
    return float(np.maximum(values.max(), -values.min()))


def _store(lines: ByteArray, start: int, words: WordArray) -> None:
    """Store one word per line (its bytes are ASCII text) at byte `start` of each line."""
    lines[:, start : start + words.dtype.itemsize].view(words.dtype)[:, 0] = words


@dataclasses.dataclass(frozen=True, slots=True)
class _FixedText:
    """Where a '%.6f' column's text sits in a line: integer part in whole words, right-aligned with its sign."""

    point: int  # the decimal point's byte
    words: int  # of four bytes before the point


@dataclasses.dataclass(frozen=True, slots=True)
class _Layout:
    """Every line's layout: the template (constant bytes, spaces where numbers go) and where each number goes.

    A covariance entry is a byte for minus signs if some entry is negative, "d.dddddddd", "e", the exponent's sign and
    two digits, or three when some entry is below 1e-99 or from 1e100 up; the nine follow one another, after ", ".
    """

    template: ByteArray
    fixed: tuple[_FixedText, ...]
    cov_start: int
    cov_signed: int  # 1 when some entry is negative
    exponent_digits: int

    @classmethod
    def of(cls, fixed: list[FloatArray], cov: FloatArray) -> _Layout:
        """The layout that fits every value (rounding is monotonic: the extremes have the widest texts)."""
        template = bytearray()
        texts: list[_FixedText] = []
        for name, values in zip(FIXED_FIELDS, fixed, strict=True):
            template += b'%s"%s": ' % (b", " if texts else b"{", name.encode())
            digits = len(f"{_biggest(values):.{FIXED_DECIMALS}f}") - 1 - FIXED_DECIMALS
            words = -(-(digits + int(np.signbit(values).any())) // 4)
            texts.append(_FixedText(len(template) + 4 * words, words))
            template += b" " * 4 * words + b"." + b" " * FIXED_DECIMALS
        extremes = [_biggest(cov)]
        small = cov[(cov > -1e-99) & (cov < 1e-99)]
        tiny = small[small != 0]
        if tiny.size:
            extremes.append(float(np.abs(tiny).min()))
        exponent_digits = max(len(b"%.8e" % value) - 12 for value in extremes)  # "d.dddddddde+" is 12 bytes
        template += b', "cov": ['
        layout = cls(np.empty(0, np.uint8), tuple(texts), len(template), int(np.signbit(cov).any()), exponent_digits)
        template += b", ".join([b" " * layout.cov_width] * COV_ENTRIES) + b"]}\n"
        return dataclasses.replace(layout, template=np.frombuffer(bytes(template), dtype=np.uint8))

    @property
    def cov_width(self) -> int:
        """Bytes of a covariance entry's text."""
        return self.cov_signed + 12 + self.exponent_digits

    def fill(self, lines: ByteArray, fixed: list[FloatArray], cov: FloatArray) -> None:
        """Write these rows' lines (fixed: t, x, y, theta; cov n x 9) into `lines` (n x template size)."""
        lines[:] = self.template
        self._write_fixed(lines, np.column_stack(fixed))
        self._write_cov(lines, cov)

    def _write_fixed(self, lines: ByteArray, values: FloatArray) -> None:
        """Write t, x, y, theta (the columns of values), rounded as '%.6f' rounds, right-aligned."""
        magnitude = np.abs(values)
        whole = np.floor(magnitude)
        fraction = magnitude - whole  # exact: the bits below the binary point
        scaled = fraction * 1e6
        millionths = np.rint(scaled)
        half = np.abs(scaled - millionths) == 0.5
        if half.any():
            halves = np.nonzero(half)
            millionths[halves] = _round_half(scaled[halves], _product_error(fraction[halves], np.float64(1e6)))
        carry = millionths == 1e6  # 0.9999996 is 1.000000
        integer = whole.astype(np.int64)
        integer += carry
        decimals = millionths.astype(np.int64)
        decimals[carry] = 0
        high = decimals // 10**4
        two, four = _TWO_DIGITS[high], _FOUR_DIGITS[decimals - high * 10**4]
        # the integer parts' words, rightmost first; a column needing fewer words than the widest has blanks here
        words = _INTEGER_WORDS[_integer_word_indices(integer, np.signbit(values), max(t.words for t in self.fixed))]
        for field, text in enumerate(self.fixed):
            for word in range(text.words):
                _store(lines, text.point - 4 * (word + 1), words[word, :, field])
            _store(lines, text.point + 1, two[:, field])
            _store(lines, text.point + 3, four[:, field])

    def _write_cov(self, lines: ByteArray, cov: FloatArray) -> None:
        """Write the covariance entries, rounded as '%.8e' rounds."""
        bits = cov.view(np.int64)
        symmetric = np.array_equal(bits[:, [1, 2, 5]], bits[:, [3, 6, 7]])  # as ekf.cov_full builds it
        values = cov[:, [0, 1, 2, 4, 5, 8]] if symmetric else cov  # then the six distinct entries are enough
        magnitude = np.abs(values)
        exponent = np.floor(np.log10(np.where(magnitude > 0, magnitude, 1.0))).astype(np.int64)  # 0 for a zero
        mantissa = _mantissa(magnitude, exponent)
        # Rounding can carry into a tenth digit (9.9999999996 is 1.00000000e+01), and just above a power of ten log10
        # can round down below its integer, one exponent too low: both make ten digits; take the next exponent. (Just
        # below one, log10 rounding up to the integer makes a mantissa a hair under 1e8: it rounds to 1e8, rightly.)
        high = mantissa >= 10**9
        if high.any():
            moved = np.nonzero(high)
            exponent[moved] += 1
            mantissa[moved] = _mantissa(magnitude[moved], exponent[moved])

        lead = mantissa // 10**8
        rest = mantissa - lead * 10**8
        middle = rest // _GROUP
        exponent += _EXPONENT_RANGE
        columns = _SYMMETRIC if symmetric else list(range(COV_ENTRIES))
        # the entries side by side, one slot each: its text and the ", " after it
        slot = self.cov_width + 2
        entries = lines[:, self.cov_start : self.cov_start + COV_ENTRIES * slot].reshape(len(lines), COV_ENTRIES, slot)
        if self.cov_signed:
            sign = np.signbit(values).view(np.uint8) * np.uint8(_MINUS - _SPACE) + np.uint8(_SPACE)
            entries[:, :, 0] = sign[:, columns]
        words = (
            _LEAD_DIGIT[lead],
            _FOUR_DIGITS[middle],
            _FOUR_DIGITS[rest - middle * _GROUP],
            _EXPONENT_WORD[exponent],
        )
        for offset, entry_words in zip((0, 2, 6, 10), words, strict=True):  # "d.", "dddd", "dddd", "e-05"
            start = self.cov_signed + offset
            cells = entries[:, :, start : start + entry_words.itemsize]
            cells.view(entry_words.dtype)[..., 0] = entry_words[:, columns]
        if self.exponent_digits == 3:  # an exponent under 100 still has two digits, as in '%.8e': a space follows
            entries[:, :, self.cov_signed + 14] = _EXPONENT_TEXT[exponent, 4][:, columns]


def _integer_word_indices(integer: IntArray, negative: npt.NDArray[np.bool_], words: int) -> IntArray:
    """Indices into _INTEGER_WORDS of the `words` words, rightmost first, of integers right-aligned with their sign
    (each fits: at most 4 * words - 1 digits if negative, 4 * words if not): shape (words, *integer.shape)."""
    indices = np.empty((words, *integer.shape), dtype=np.int64)
    rest = integer
    for word in range(words):
        place = _GROUP**word  # of the word's last digit
        quotient = rest // _GROUP
        group = rest - quotient * _GROUP
        rest = quotient
        leading = _LEADING + negative * _GROUP + group
        if not word:  # the units word: the number's leading digits at least
            indices[word] = np.where(integer >= _GROUP, group, leading)
        else:
            blank = _BLANK + (negative & (integer >= place // 10))  # the minus of a four-digit group on its right
            indices[word] = np.where(integer >= place * _GROUP, group, np.where(integer >= place, leading, blank))
    return indices


def _mantissa(magnitude: FloatArray, exponent: IntArray) -> IntArray:
    """magnitude * 10**(8 - exponent) rounded to an integer as '%.8e' rounds (see the module docstring)."""
    power = 8 - exponent
    one_step = power.min() >= -_EXACT_POWERS and power.max() <= _EXACT_POWERS
    if one_step and power.min() >= 0:  # the usual case: every entry in [1e-14, 1e9)
        scaled = magnitude * _POW10[power]
    else:
        scaled = _scaled(magnitude.ravel(), power.ravel()).reshape(power.shape)
    rounded: FloatArray = np.rint(scaled)
    half = np.abs(scaled - rounded) == 0.5
    if not one_step:
        half &= np.abs(power) <= _EXACT_POWERS  # only a value scaled with one rounding can be settled exactly
    if half.any():
        halves = np.nonzero(half)
        factor = _POW10[np.abs(power[halves])]
        up = power[halves] >= 0
        # up: scaled = fl(m * 10**k). Down: scaled = fl(m / 10**k), and the quotient's excess has the sign of
        # m - scaled * 10**k = (m - fl(scaled * 10**k)) - error, the first difference exact by Sterbenz's lemma
        error = _product_error(np.where(up, magnitude[halves], scaled[halves]), factor)
        excess = np.where(up, error, (magnitude[halves] - scaled[halves] * factor) - error)
        rounded[halves] = _round_half(scaled[halves], excess)
    return rounded.astype(np.int64)


def _scaled(magnitude: FloatArray, power: IntArray) -> FloatArray:
    """magnitude * 10**power in steps by exact powers of ten, each rounding once (one step for |power| <= 22)."""
    scaled = magnitude.copy()
    rest = power.copy()
    steps = np.arange(power.size)
    while steps.size:  # more than one step only below 1e-14 or from 1e31 up
        step = np.clip(rest[steps], -_EXACT_POWERS, _EXACT_POWERS)
        up, down = step >= 0, step < 0
        scaled[steps[up]] *= _POW10[step[up]]
        scaled[steps[down]] /= _POW10[-step[down]]  # a division rounds once, a product by 10**-k (inexact) twice
        rest[steps] -= step
        steps = steps[rest[steps] != 0]
    return scaled


def _round_half(scaled: FloatArray, excess: FloatArray) -> FloatArray:
    """Integers nearest to exact values lying `excess` above half-way points `scaled`, ties (excess 0) to even."""
    below = np.floor(scaled)
    return np.where(excess > 0, below + 1.0, np.where(excess < 0, below, np.rint(scaled)))


def _product_error(a: FloatArray, b: FloatArray | np.float64) -> FloatArray:
    """Exact a*b minus fl(a*b) (Dekker's two-product; a and b small enough that times 2**27 they stay finite)."""
    a_high, a_low = _split(a)
    b_high, b_low = _split(b)
    return ((a_high * b_high - a * b) + a_high * b_low + a_low * b_high) + a_low * b_low


def _split(a: FloatArray | np.float64) -> tuple[FloatArray, FloatArray]:
    """a as high + low, each with at most 26 significant bits (Veltkamp)."""
    c = _SPLITTER * a
    high = c - (c - a)
    return np.asarray(high), np.asarray(a - high)
