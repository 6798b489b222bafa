"""Bulk parsing of the sensor log's standard lines: wheels, truth and ips lines in the exact shape `encode` writes.

A log is mostly wheel samples; parsing each line with json.loads costs microseconds a line. Here the lines of one
type are checked and parsed together, at C speed, as one ASCII byte string: the template's constant parts that hold
number characters (', "type": "wheels", "ticks": [', ...) are replaced by marker bytes; once the numbers are deleted
every line must read exactly as the template's constants (the shape check), no two constants may touch (no number
missing) and there must be exactly one run of number characters per number (none inside a constant). The numbers are
then checked against the JSON grammar where a C strtod is more lenient, and parsed by numpy's C reader in one call.
A batch that fails any check, or any line not in a template's shape, goes through the per-line reader instead, so
the result (values, errors and their line numbers) is the same as parsing every line with json.loads.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

NUMBER_CHARS = "0123456789.-+eE"
NUMBER_BYTES = NUMBER_CHARS.encode("ascii")
PREFIX = '{"t": '
MARKERS = range(1, 8)  # control characters that stand for constants while checking; a text holding any is refused


@dataclass(frozen=True, slots=True)
class Template:
    """A line shape: PREFIX, then numbers between constant strings, ending with `suffix`."""

    kind: str
    separators: tuple[str, ...]  # the constants between consecutive numbers, the first holds the type
    suffix: str
    integer_tail: int = 0  # how many of the last numbers must be JSON integers

    @property
    def marker(self) -> str:
        """The substring that makes a line a candidate for this template."""
        return self.separators[0]


WHEELS = Template("wheels", (', "type": "wheels", "ticks": [', ", ", ", ", ", "), "]}", integer_tail=4)
TRUTH = Template("truth", (', "type": "truth", "x": ', ', "y": ', ', "theta": '), "}")
IPS = Template("ips", (', "type": "ips", "x": ', ', "y": ', ', "z": ', ', "t_meas": '), "}")
TEMPLATES = (WHEELS, TRUTH, IPS)


@dataclass(frozen=True, slots=True)
class _Coding:
    """How a template's lines are checked and reduced to numbers, as bytes (see _marked and _parse_numbers)."""

    marked: tuple[tuple[bytes, bytes], ...]  # separators replaced by a marker byte, and their marker, longest first
    shape: bytes  # a line once its numbers are deleted (with the markers in)
    classes: bytes  # translation table: number bytes to '#', bytes that open a number's place to 'b', others '.'
    commas: bytes  # translation table: markers and line ends to commas, the constant bytes below deleted
    constant_bytes: bytes
    tick_skeleton: bytes  # the integer tail once digits and '-' are deleted (empty unless integer_tail)


def _coding(template: Template) -> _Coding:
    """The checks of a template: separators holding number characters ('e' in "type") become markers, and so do
    separators holding, before their end, a byte that ends a constant in front of a number (' ' in ', "y": ')."""
    seps = template.separators
    code = {sep: chr(MARKERS[i]) for i, sep in enumerate(sep for sep in seps if "e" in sep or "E" in sep)}
    while True:
        constants = [PREFIX, *(code.get(sep, sep) for sep in seps), template.suffix]
        openers = {constant[-1] for constant in constants[:-1]}
        inner = [sep for sep in seps if sep not in code and openers & set(sep[:-1])]
        if not inner:
            break
        code[inner[0]] = chr(MARKERS[len(code)])
    assert not openers & set(PREFIX[:-1] + template.suffix), template.kind  # (they cannot be marked)
    # every constant must give exactly one comma between two numbers (the first none, the last none)
    commas_in = [sum(c in code.values() or c == "," for c in constant) for constant in constants]
    assert commas_in == [0] + [1] * len(seps) + [0], template.kind
    classes = bytes(
        ord("#") if chr(b) in NUMBER_CHARS else ord("b") if chr(b) in openers else ord(".") for b in range(256)
    )
    commas = bytearray(range(256))
    for c in [*code.values(), "\n"]:
        commas[ord(c)] = ord(",")
    deleted = set("".join(constants)) - set(code.values()) - {","}
    assert not deleted & set(NUMBER_CHARS), template.kind  # deleting them would cut into the numbers
    tail = "".join(constants[-1 - template.integer_tail :]) if template.integer_tail else ""
    return _Coding(
        tuple((sep.encode("ascii"), code[sep].encode("ascii")) for sep in sorted(code, key=len, reverse=True)),
        "".join(constants).encode("ascii"),
        classes,
        bytes(commas),
        "".join(sorted(deleted)).encode("ascii"),
        tail.encode("ascii"),
    )


_CODINGS = {template.kind: _coding(template) for template in TEMPLATES}


def parse_batch(template: Template, lines: list[str]) -> npt.NDArray[np.float64] | None:
    """The numbers of lines (without newline) that all have the template's shape, one row a line; None otherwise."""
    marked = _marked(template, lines)
    if marked is None:
        return None
    return _parse_numbers(template, marked, len(lines))


def parse_wheels(lines: list[str]) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.int64]] | None:
    """Times and cumulative ticks (n x 4) of wheels lines in the exact standard shape; None if any is not."""
    marked = _marked(WHEELS, lines)
    if marked is None:
        return None
    # ticks must be JSON integers: no fraction, no exponent; with digits and '-' deleted, each line's tail is bare
    coding = _CODINGS[WHEELS.kind]
    if marked.translate(None, b"0123456789-").count(coding.tick_skeleton) != len(lines):
        return None
    values = _parse_numbers(WHEELS, marked, len(lines))
    if values is None:
        return None
    exact = values[:, 1:]
    # JSON integers read as floats (much faster than int()): exact below 2^53
    if not np.all(np.abs(exact) < 2.0**53):
        return None
    return np.ascontiguousarray(values[:, 0]), exact.astype(np.int64)


def _marked(template: Template, lines: list[str]) -> bytes | None:
    """The lines as one ASCII text, separators replaced by their markers, if every line has exactly the template's
    shape: its constants, in order, with one run of number characters (non-empty) in each number's place."""
    if not lines:
        return None
    block = "\n".join(lines)
    if not block.isascii():  # the template and JSON numbers are ASCII
        return None
    marked = block.encode("ascii")
    if any(marker in marked for marker in MARKERS):  # the markers must not occur in the text itself
        return None
    coding = _CODINGS[template.kind]
    for sep, marker in coding.marked:
        marked = marked.replace(sep, marker)
    # with the numbers deleted, every line reads as the template's constants
    if marked.translate(None, NUMBER_BYTES) != b"\n".join([coding.shape] * len(lines)):
        return None
    # every run of number bytes opens right after a constant's last byte ('b#'; never '.#', nor at a line's start),
    # and there are as many as numbers: the bytes that open a number's place occur only there (the shape), so each
    # place holds exactly one run, none is empty and no constant has number bytes inside
    classes = (b"\n" + marked).translate(coding.classes)
    if b".#" in classes or classes.count(b"b#") != len(lines) * (len(template.separators) + 1):
        return None
    return marked


def _parse_numbers(template: Template, marked: bytes, count: int) -> npt.NDArray[np.float64] | None:
    """The numbers of checked lines (see _marked), one row a line, if each is a JSON number; None otherwise."""
    coding = _CODINGS[template.kind]
    text = b"," + marked.translate(coding.commas, coding.constant_bytes) + b","
    if not json_numbers(text):
        return None
    try:
        # the C parser reads what float() reads, correctly rounded; it refuses a token float() would refuse
        with warnings.catch_warnings(action="error"):
            values = np.fromstring(text[1:-1], dtype=np.float64, sep=",")
    except (ValueError, DeprecationWarning):
        return None
    width = len(template.separators) + 1
    if len(values) != count * width:
        return None
    return values.reshape(-1, width)


def json_numbers(text: bytes) -> bool:
    """Whether a comma-separated (and comma-enclosed) list of non-empty tokens made of NUMBER_CHARS holds only tokens
    that are JSON numbers, where a C strtod would read the same value as json.loads does.

    strtod also reads '+1', '.5', '5.', '1.e3' and leading zeros, which JSON rejects, and reads the JSON integer
    '-0' as -0.0 where json.loads gives the integer 0: those are refused. What strtod refuses (e.g. '1e', '1-2')
    fails later.
    """
    if b"+" in text and text.count(b"+") != text.count(b"e+") + text.count(b"E+"):
        return False
    # every '.' between two digits (no '.5', '-.5', '5.', '5.e3'); 'd.d' cannot overlap in valid text
    if text.count(b".") != text.translate(_D_FOR_DIGITS).count(b"d.d"):
        return False
    if b",-0," in text:
        return False
    zeros = text.translate(_ONE_FOR_DIGITS, b"-")  # leading zeros: ",0" or ",-0" followed by a digit
    return b",00" not in zeros and b",01" not in zeros


_D_FOR_DIGITS = bytes.maketrans(b"0123456789", b"dddddddddd")
_ONE_FOR_DIGITS = bytes.maketrans(b"23456789", b"11111111")


# What each line is, in file order. Events: wheels, truth, other (what logfile.Columns keeps); while parsing also:
WHEELS_KIND, TRUTH_KIND, OTHER_KIND = 1, 2, 0
IPS_LINE, PER_LINE, NO_EVENT = 3, 4, -1  # a bulk-parsed fix, a line for the per-line reader, a line without event


@dataclass(frozen=True, slots=True)
class Bulk:
    """The standard lines parsed: each line's kind, and the numbers of the wheels, truth and ips lines in order."""

    kinds: npt.NDArray[np.int8]  # WHEELS_KIND, TRUTH_KIND, IPS_LINE or PER_LINE
    wheels_t: npt.NDArray[np.float64]
    wheels_ticks: npt.NDArray[np.int64]  # n x 4
    truth: npt.NDArray[np.float64]  # n x 4: t, x, y, theta
    ips: npt.NDArray[np.float64]  # n x 5: t, x, y, z, t_meas


def parse_standard(lines: list[str]) -> Bulk:
    """Sort lines (without newline) by template and parse each template's lines together.

    A template whose lines are not all in its exact shape has all of them marked PER_LINE.
    """
    wheels_mark, truth_mark, ips_mark = (template.marker for template in TEMPLATES)
    kinds = np.array(
        [
            WHEELS_KIND
            if wheels_mark in line
            else TRUTH_KIND
            if truth_mark in line
            else IPS_LINE
            if ips_mark in line
            else PER_LINE
            for line in lines
        ],
        dtype=np.int8,
    )
    rows = np.flatnonzero(kinds == WHEELS_KIND)
    wheels = parse_wheels([lines[i] for i in rows.tolist()])
    if wheels is None:
        kinds[rows] = PER_LINE
        wheels = (np.zeros(0), np.zeros((0, 4), dtype=np.int64))
    rows = np.flatnonzero(kinds == TRUTH_KIND)
    truth = parse_batch(TRUTH, [lines[i] for i in rows.tolist()])
    if truth is None:
        kinds[rows] = PER_LINE
        truth = np.zeros((0, 4))
    rows = np.flatnonzero(kinds == IPS_LINE)
    ips = parse_batch(IPS, [lines[i] for i in rows.tolist()])
    if ips is None:
        kinds[rows] = PER_LINE
        ips = np.zeros((0, 5))
    return Bulk(kinds, wheels[0], wheels[1], truth, ips)


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
    "WHEELS",
    "WHEELS_KIND",
    "Bulk",
    "Template",
    "merge_in_order",
    "parse_batch",
    "parse_standard",
    "parse_wheels",
]
