"""Bulk parsing of the sensor log's standard lines: wheels, truth, ips and twist lines in the shape `encode` writes.

A log is mostly wheel samples, and json.loads costs microseconds a line. Here every line of the text is checked and
parsed at C speed (numpy over blocks of about a megabyte of whole lines, no Python loop over lines), and a line is
taken only when it reads exactly as a template: its constant strings with one JSON number in each number's place.

Shape. Every constant between two numbers starts with ',' and the first and the last hold none, so a line of a
template's shape holds exactly the template's commas, and they place its constants: the line's first comma starts
the constant after the first number, and so on. A candidate line has that many commas; each constant is compared
where its comma puts it (the first at the line's start, the last at its end), and what lies between two constants is
a number's place. Whatever the line holds, if each constant is where the commas put it and each place holds a JSON
number, the line is exactly the template's shape: the checks do not trust the commas, they only use them to look.

Numbers. A place must hold, as JSON has it without exponent, -?(0|[1-9][0-9]*)(\\.[0-9]+)?, in 1 to 16 bytes with the
'.', if any, among the last 8. It is read as the little-endian 64-bit word that ends where it ends (and the word
before, for a longer place), masked to its bytes, and checked eight bytes at a time (SWAR): only a '-' first and one
'.' may be other than digits. The '-' is masked out, the bytes in front of the '.' are moved one byte on, over it, and
the digits are summed into the mantissa by three multiply-and-shift steps. The integer part is then checked to have
digits and no leading zero (a mantissa of d digits is at least 10^(d-1) unless its first digit is 0). A float's place
has at most 15 digits: its mantissa m is exact as a double, as is 10^k for its k fraction digits, and the one IEEE
division m / 10^k rounds correctly, as float() of the text does; without a fraction json.loads gives an int, whose
float() is m exactly (and the integer -0 is 0, not -0.0). An integer's place has no fraction, and 16 digits fit an
int64.

A line passing all of this decodes with json.loads to the same event; every other line (the meta, blank lines, other
types, exponents, damage, non-ASCII) is left to the per-line reader, which reports problems with their line numbers.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

# What each line is, in file order. Events: wheels, truth, other (what logfile.Columns keeps); while parsing also:
WHEELS_KIND, TRUTH_KIND, OTHER_KIND = 1, 2, 0
IPS_LINE, PER_LINE, NO_EVENT = 3, 4, -1  # a bulk-parsed fix, a line for the per-line reader, a line without event
TWIST_LINE = 5  # a bulk-parsed twist sample

NEWLINE, COMMA, MINUS, DOT = b"\n,-."
FLOAT_DIGITS = 15  # at most 15 digits are below 2^53: exact as a double
WORD = 8  # bytes in a 64-bit word
MAX_BYTES = 2 * WORD  # the bytes of a number's place that are read (two words)


@dataclass(frozen=True, slots=True)
class Template:
    """A standard line: numbers between constants, each number a float ('f') or an integer ('i')."""

    kind: int
    constants: tuple[str, ...]  # before the first number, between numbers, after the last
    places: str

    @property
    def commas(self) -> list[int]:
        """For each constant between numbers, its first comma's rank among the line's commas; then their count."""
        counts = [constant.count(",") for constant in self.constants[1:-1]]
        return [sum(counts[:i]) for i in range(len(counts) + 1)]


def _checked(template: Template) -> Template:
    """The template, if the shape check can rely on it: the first and last constants without a comma, the others
    starting with one, all ASCII and not ending in NUL (see _at)."""
    first, *between, last = template.constants
    if (
        len(template.places) != len(between) + 1
        or "," in first + last
        or not all(constant.startswith(",") for constant in between)
        or not all(constant.isascii() and constant[-1] != "\0" for constant in template.constants)
    ):
        raise ValueError(f"not a template the bulk reader can check: {template}")
    return template


WHEELS = _checked(Template(WHEELS_KIND, ('{"t": ', ', "type": "wheels", "ticks": [', ", ", ", ", ", ", "]}"), "fiiii"))
TRUTH = _checked(Template(TRUTH_KIND, ('{"t": ', ', "type": "truth", "x": ', ', "y": ', ', "theta": ', "}"), "ffff"))
IPS = _checked(
    Template(IPS_LINE, ('{"t": ', ', "type": "ips", "x": ', ', "y": ', ', "z": ', ', "t_meas": ', "}"), "fffff")
)
TWIST = _checked(Template(TWIST_LINE, ('{"t": ', ', "type": "twist", "vx": ', ', "vy": ', ', "wz": ', "}"), "ffff"))
TEMPLATES = (WHEELS, TRUTH, IPS, TWIST)


@dataclass(frozen=True, slots=True)
class Bulk:
    """The standard lines parsed: each line's kind and end, and the numbers of the wheels, truth, ips, twist lines."""

    kinds: npt.NDArray[np.int8]  # WHEELS_KIND, TRUTH_KIND, IPS_LINE, TWIST_LINE or PER_LINE
    line_ends: npt.NDArray[np.intp]  # where each line's newline is (the text's length for a last line without)
    wheels_t: npt.NDArray[np.float64]
    wheels_ticks: npt.NDArray[np.int64]  # n x 4
    truth: npt.NDArray[np.float64]  # n x 4: t, x, y, theta
    ips: npt.NDArray[np.float64]  # n x 5: t, x, y, z, t_meas
    twists: npt.NDArray[np.float64]  # n x 4: t, vx, vy, wz


@dataclass(frozen=True, slots=True)
class _Text:
    """A text of lines, and where its lines and commas are."""

    text: bytes
    chars: npt.NDArray[np.uint8]
    words: npt.NDArray[np.uint64]  # words[i]: the little-endian word of the 8 bytes ending at i (0 before the text)
    line_starts: npt.NDArray[np.intp]
    line_ends: npt.NDArray[np.intp]
    commas: npt.NDArray[np.intp]
    first_comma: npt.NDArray[np.intp]  # per line, the rank of its first comma (of the next one's, if it has none)
    comma_count: npt.NDArray[np.intp]


BLOCK = 1 << 20  # bytes parsed at a time: every temporary stays small, in the cache and in reused memory


def parse_standard(text: bytes) -> Bulk:
    """Find and parse the standard lines of a text of lines, each ending with '\\n' except perhaps the last."""
    blocks, start = [], 0
    while start < len(text):
        end = text.find(b"\n", start + BLOCK) + 1 or len(text)  # blocks of whole lines
        blocks.append((start, _parse_block(text[start:end])))
        start = end
    if not blocks:
        blocks.append((0, _parse_block(b"")))
    kinds = np.concatenate([block.kinds for _, block in blocks])
    line_ends = np.concatenate([block.line_ends + start for start, block in blocks])
    wheels, ticks, truth, ips, twists = (np.concatenate([block.numbers[i] for _, block in blocks]) for i in range(5))
    return Bulk(kinds, line_ends, wheels[:, 0], ticks, truth, ips, twists)


@dataclass(frozen=True, slots=True)
class _Block:
    """A block of lines parsed: as Bulk, with line ends from the block's start."""

    kinds: npt.NDArray[np.int8]
    line_ends: npt.NDArray[np.intp]
    numbers: tuple[npt.NDArray[Any], ...]  # wheels' floats and integers, truth's, ips' and twists' floats


def _parse_block(text: bytes) -> _Block:
    """Parse a block of whole lines (see parse_standard)."""
    chars = np.frombuffer(text, dtype=np.uint8)
    line_ends = np.flatnonzero(chars == NEWLINE)
    if len(chars) and chars[-1] != NEWLINE:
        line_ends = np.append(line_ends, len(chars))
    line_starts = np.zeros_like(line_ends)
    line_starts[1:] = line_ends[:-1] + 1
    commas = np.flatnonzero(chars == COMMA)
    first_comma = np.searchsorted(commas, line_starts)
    padded = np.zeros(MAX_BYTES + len(chars), dtype=np.uint8)  # zeros before the text: every word can be read
    padded[MAX_BYTES:] = chars
    words = np.ndarray((len(chars) + 1,), dtype="<u8", buffer=padded, offset=MAX_BYTES - WORD, strides=(1,))
    lines = _Text(
        text, chars, words, line_starts, line_ends, commas, first_comma, np.diff(first_comma, append=len(commas))
    )
    kinds = np.full(len(line_ends), PER_LINE, dtype=np.int8)
    (wheels, ticks), (truth, _), (ips, _), (twists, _) = (_parse(lines, kinds, template) for template in TEMPLATES)
    return _Block(kinds, line_ends, (wheels, ticks, truth, ips, twists))


def _parse(
    lines: _Text, kinds: npt.NDArray[np.int8], template: Template
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.int64]]:
    """The float and the integer numbers (one row a line, in places' order) of the lines that read exactly as the
    template; those lines are marked with the template's kind."""
    first, *between, last = (constant.encode("ascii") for constant in template.constants)
    *ranks, count = template.commas
    floats = [place for place, kind in enumerate(template.places) if kind == "f"]
    integers = [place for place, kind in enumerate(template.places) if kind == "i"]
    shortest = sum(map(len, template.constants)) + len(template.places)
    rows = np.flatnonzero((lines.comma_count == count) & (lines.line_ends - lines.line_starts >= shortest))
    # where the constants between the numbers start: at commas (one row a constant)
    at = lines.commas[lines.first_comma[rows] + np.array(ranks, dtype=np.intp)[:, None]]
    # the first of them names the type: the lines without it are left first
    ends = lines.line_ends[rows]
    good = _between(lines, at[0], ends, between[0])
    rows, at, ends = rows[good], at[:, good], ends[good]
    starts = lines.line_starts[rows]
    good = _at(lines, starts, first) & _at(lines, ends - len(last), last)
    place_starts = np.empty((len(template.places), len(rows)), dtype=np.intp)
    place_starts[0] = starts + len(first)
    place_ends = np.empty_like(place_starts)
    place_ends[:-1], place_ends[-1] = at, ends - len(last)
    for place, constant in enumerate(between):
        place_starts[place + 1] = at[place] + len(constant)
        if place:
            good &= _between(lines, at[place], ends, constant)
    rows, place_starts, place_ends = rows[good], place_starts[:, good], place_ends[:, good]
    float_values, float_fits = _numbers(lines, place_starts[floats], place_ends[floats], fractions=True)
    integer_values, integer_fits = _numbers(lines, place_starts[integers], place_ends[integers], fractions=False)
    good = np.logical_and(float_fits.all(axis=0), integer_fits.all(axis=0))
    kinds[rows[good]] = template.kind
    return float_values[:, good].T, integer_values[:, good].T


def _between(
    lines: _Text, commas: npt.NDArray[np.intp], ends: npt.NDArray[np.intp], constant: bytes
) -> npt.NDArray[np.bool_]:
    """Whether `constant`, which starts with a ',', stands at each comma, within its line."""
    inside = commas + len(constant) <= ends
    return inside & _at(lines, np.minimum(commas, len(lines.text) - len(constant)) + 1, constant[1:])


def _at(lines: _Text, positions: npt.NDArray[np.intp], constant: bytes) -> npt.NDArray[np.bool_]:
    """Whether `constant` stands at each position (each at most len(text) - len(constant))."""
    if len(constant) == 1:
        return np.asarray(lines.chars[positions] == constant[0])
    if len(constant) <= WORD:  # the word ending with it, its bytes in front shifted out
        word = lines.words[positions + len(constant)] >> _U(8 * (WORD - len(constant)))
        return np.asarray(word == _U(int.from_bytes(constant, "little")))
    text = lines.text
    if len(text) < len(constant):
        return np.zeros(len(positions), dtype=np.bool_)
    # every window of the text as one fixed-width string, without copying. (Fixed-width strings compare without
    # trailing NULs; equal to a constant whose last byte is not NUL, a window of its width holds exactly it.)
    windows = np.ndarray((len(text) - len(constant) + 1,), dtype=f"S{len(constant)}", buffer=text, strides=(1,))
    return np.asarray(windows[positions] == constant, dtype=np.bool_)


_U = np.uint64
_ALL, _ONES, _HIGH_BITS = _U(2**64 - 1), _U(0x0101010101010101), _U(0x8080808080808080)
_POW10 = np.array([10**k for k in range(MAX_BYTES + 1)], dtype=np.uint64)
_POW10_FLOAT = np.array([float(10**k) for k in range(WORD + 1)])  # exact: 10^k = 2^k 5^k and 5^k < 2^53


def _not_digits(word: npt.NDArray[np.uint64]) -> npt.NDArray[np.uint64]:
    """The high bit of each byte that is not '0'..'9'. (No carry crosses a byte: (b & 0x7f) + 0x76 <= 0xf5.)"""
    offset = word ^ (_ONES * _U(ord("0")))  # a digit's byte is now 0..9
    return (((offset & ~_HIGH_BITS) + _ONES * _U(0x80 - 10)) | offset) & _HIGH_BITS


def _equal(word: npt.NDArray[np.uint64], byte: int) -> npt.NDArray[np.uint64]:
    """The high bit of each byte equal to `byte`. (No carry crosses a byte: (b & 0x7f) + 0x7f <= 0xfe.)"""
    zero = word ^ (_ONES * _U(byte))
    return ~(((zero & ~_HIGH_BITS) + ~_HIGH_BITS) | zero) & _HIGH_BITS


def _digit_sum(word: npt.NDArray[np.uint64]) -> npt.NDArray[np.uint64]:
    """The value of a word of digits and zero bytes: sum of (byte & 0x0f) * 10^(7 - i) over its bytes i, first first.

    Pairs, then quads, then the eight are combined by one multiply-and-shift each, no lane overflowing into the next:
    9 * 11 < 2^8, 99 * 101 < 2^16, 9999 * 10001 < 2^32.
    """
    word = ((word & (_ONES * _U(0x0F))) * _U(10 << 8 | 1)) >> _U(8)
    word = ((word & _U(0x00FF00FF00FF00FF)) * _U(100 << 16 | 1)) >> _U(16)
    return ((word & _U(0x0000FFFF0000FFFF)) * _U(10000 << 32 | 1)) >> _U(32)


def _byte_mask(flags: npt.NDArray[np.uint64]) -> npt.NDArray[np.uint64]:
    """Whole bytes where the high bit is set."""
    return (flags >> _U(7)) * _U(0xFF)


def _nonzero(word: npt.NDArray[np.uint64]) -> npt.NDArray[np.uint64]:
    """1 where the word is not 0, else 0: of x and -x, one has the top bit when x is not 0."""
    return (word | (_U(0) - word)) >> _U(63)


def _numbers(
    lines: _Text, starts: npt.NDArray[np.intp], ends: npt.NDArray[np.intp], *, fractions: bool
) -> tuple[npt.NDArray[Any], npt.NDArray[np.bool_]]:
    """The numbers at places [starts, ends), as floats (fractions allowed) or integers (none), and whether each is a
    JSON number fit for its place (see the module's docstring).

    Each place's last word is read, and the word before for a place longer than a word; a '.' must be in the last
    word (at most 7 fraction digits). Bytes are marked by their high bit (`first`: the place's first byte, if it is
    in the word). All is done in uint64: numpy casts element by element where types mix.
    """
    shape = starts.shape
    starts, ends = starts.ravel(), ends.ravel()
    length = ends - starts
    word = lines.words[ends]
    # (a shift by 64 or more gives 0: nothing kept of an empty place, and no first byte in a longer one's last word)
    keep = _ALL << ((WORD - np.minimum(length, WORD)) * 8).astype(np.uint64)
    first = _U(0x80) << ((WORD - length) * 8).astype(np.uint64)
    not_digit = _not_digits(word) & keep
    minus = _equal(word, MINUS) & first
    value = word & keep & ~_byte_mask(minus)
    if fractions:  # one '.' at most, not last: the bytes in front of it are moved one byte on, over it
        dot = _equal(word, DOT) & keep
        readable = ((not_digit & ~dot) == minus) & ((dot & (dot - _U(1))) == 0) & (dot < _U(1 << 63))
        has_dot = _nonzero(dot)
        dot_bit = dot >> _U(7)
        before = dot_bit - has_dot  # the bytes in front of the '.' (none without one)
        after = ~(before | dot_bit * _U(0xFF))  # the bytes behind it (all without one)
        fraction = (((after & _ONES) * _ONES) >> _U(56)) * has_dot  # how many: the bytes' sum lands in the top byte
        value = (value & after) | ((value & before) << _U(8))
    else:
        readable = not_digit == minus
        has_dot = fraction = np.zeros_like(word)
    mantissa = _digit_sum(value)
    readable &= (length >= 1) & (length <= MAX_BYTES)
    long = np.flatnonzero(readable & (length > WORD))
    if len(long):  # the word before: digits, but for a '-' first (no '.' this far from the end)
        gap = ((2 * WORD - length[long]) * 8).astype(np.uint64)
        high = lines.words[ends[long] - WORD]
        high_keep, high_first = _ALL << gap, _U(0x80) << gap
        minus[long] = high_minus = _equal(high, MINUS) & high_first
        readable[long] &= (_not_digits(high) & high_keep) == high_minus
        high &= high_keep & ~_byte_mask(high_minus)
        moved = has_dot[long]  # its last byte goes over the '.' too
        mantissa[long] = _digit_sum(high << _U(8) * moved) * _U(10**WORD) + _digit_sum(
            value[long] | (high >> _U(56)) * moved
        )
    negative = _nonzero(minus)
    # an integer part, without a leading zero: below 10^(digits - 1) the first digit is 0
    digits = length.astype(np.uint64) - negative - has_dot
    whole_digits = digits - fraction
    lowest = _POW10[np.minimum(digits - _U(1), _U(MAX_BYTES)).astype(np.intp)]
    readable &= (whole_digits >= 1) & (whole_digits <= MAX_BYTES) & ((whole_digits < 2) | (mantissa >= lowest))
    if fractions:
        readable &= digits <= FLOAT_DIGITS
        # mantissa / 10^k: both exact doubles, one correctly rounded division; json.loads reads the integer -0 as 0
        values = mantissa.astype(np.float64) / _POW10_FLOAT[fraction.astype(np.intp)]
        sign = (negative & _nonzero(fraction | mantissa)) << _U(63)
        values = (values.view(np.uint64) ^ sign).view(np.float64)
    else:  # below 10^16; negated as two's complement: (x ^ -1) + 1
        values = ((mantissa ^ (_U(0) - negative)) + negative).view(np.int64)
    return values.reshape(shape), readable.reshape(shape)


def merge_in_order(
    kinds: npt.NDArray[np.int8], kind: int, extra_lines: list[int], *pairs: tuple[npt.NDArray[Any], npt.NDArray[Any]]
) -> list[npt.NDArray[Any]]:
    """A kind's columns: (bulk rows, rows of lines `extra_lines` read one by one) pairs, merged in file order."""
    lines_of_kind = np.flatnonzero(kinds == kind)
    from_extra = np.isin(lines_of_kind, np.array(extra_lines))
    merged = []
    for bulk, extra in pairs:
        out = np.empty((len(lines_of_kind), *bulk.shape[1:]), dtype=bulk.dtype)
        out[~from_extra] = bulk
        out[from_extra] = extra
        merged.append(out)
    return merged


__all__ = [
    "IPS",
    "IPS_LINE",
    "NO_EVENT",
    "OTHER_KIND",
    "PER_LINE",
    "TEMPLATES",
    "TRUTH",
    "TRUTH_KIND",
    "TWIST",
    "TWIST_LINE",
    "WHEELS",
    "WHEELS_KIND",
    "Bulk",
    "Template",
    "merge_in_order",
    "parse_standard",
]
