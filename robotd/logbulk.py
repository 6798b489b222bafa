"""Bulk parsing of the sensor log's standard lines: wheels, truth and ips lines in the exact shape `encode` writes.

A log is mostly wheel samples; parsing each line with json.loads costs microseconds a line. Here the lines of one
type are checked and parsed together, at C speed: the template's constant parts ('{"t": ', ', "type": "wheels",
"ticks": [', ...) are replaced by marker characters, and once the numbers are deleted the markers that remain must be
exactly the template's, line after line (the shape check); the numbers are then parsed by json.loads as one array
(the JSON grammar check). A batch that fails either check, or any line not in a template's shape, goes through the
per-line reader instead, so the result (values, errors and their line numbers) is the same as parsing every line
with json.loads.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

NUMBER_CHARS = "0123456789.-+eE"
_DELETE_NUMBERS = str.maketrans("", "", NUMBER_CHARS)
PREFIX = '{"t": '


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


def parse_batch(template: Template, lines: list[str]) -> npt.NDArray[np.float64] | None:
    """The numbers of lines (without newline) that all have the template's shape, one row a line; None otherwise."""
    text = _numbers_text(template, lines)
    if text is None:
        return None
    try:
        values = np.array(list(map(float, text[1:-1].split(","))), dtype=np.float64)
    except ValueError:
        return None
    width = len(template.separators) + 1
    if len(values) != len(lines) * width:
        return None
    return values.reshape(-1, width)


def parse_wheels(lines: list[str]) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.int64]] | None:
    """Times and cumulative ticks (n x 4) of wheels lines in the exact standard shape; None if any is not."""
    text = _numbers_text(WHEELS, lines)
    if text is None:
        return None
    tokens = text[1:-1].split(",")
    if len(tokens) != 5 * len(lines):
        return None
    times = tokens[0::5]
    del tokens[0::5]
    if any(c in "".join(tokens) for c in ".eE+"):  # ticks must be JSON integers: no fraction, no exponent
        return None
    try:
        t = np.array(list(map(float, times)), dtype=np.float64)
        # JSON integers read through float() (several times faster than int()): exact below 2^53
        exact = np.array(list(map(float, tokens)), dtype=np.float64)
    except ValueError:
        return None
    if not np.all(np.abs(exact) < 2.0**53):
        return None
    return t, exact.astype(np.int64).reshape(-1, 4)


def _numbers_text(template: Template, lines: list[str]) -> str | None:
    """',n1,n2,...,' : every line's numbers in order, if every line has exactly the template's shape."""
    if not lines:
        return None
    block = "\n".join(lines)
    if any(chr(c) in block for c in range(1, 8)):  # the markers must not occur in the text itself
        return None
    # constants holding 'e' or 'E' (number characters, e.g. in "type") become one marker character each, longest
    # first; all other constants stay as they are: once the numbers are deleted, every line must read exactly as
    # the template's constants
    lettered = sorted({sep for sep in template.separators if "e" in sep or "E" in sep}, key=len, reverse=True)
    code = {sep: chr(2 + i) for i, sep in enumerate(lettered)}
    for sep in lettered:
        block = block.replace(sep, code[sep])
    shape = PREFIX + "".join(code.get(sep, sep) for sep in template.separators) + template.suffix
    if block.translate(_DELETE_NUMBERS) != "\n".join([shape] * len(lines)):
        return None
    # the numbers, comma-separated: markers and line ends become commas, the constants' other characters go
    table: dict[int, str | None] = dict.fromkeys(map(ord, set(shape) - set(code.values()) - {","}))
    table.update({ord(c): "," for c in code.values()})
    table[ord("\n")] = ","
    text = "," + block.translate(table) + ","
    return text if json_numbers(text) else None


def json_numbers(text: str) -> bool:
    """Whether a comma-separated (and comma-enclosed) list of tokens made of NUMBER_CHARS holds only tokens that are
    JSON numbers, where float() and int() would read the same value as json.loads does.

    float() also reads '+1', '.5', '5.', '1.e3' and leading zeros, which JSON rejects, and reads the JSON integer
    '-0' as -0.0 where json.loads gives the integer 0: those are refused. What float() refuses (e.g. '1e', '1-2')
    raises later.
    """
    if text.count("+") != text.count("e+") + text.count("E+"):
        return False
    if ",." in text or "-." in text or ".," in text or ".e" in text or ".E" in text or ",-0," in text:
        return False
    digits = text.translate(_ONE_FOR_DIGITS)  # leading zeros: ",0" or ",-0" followed by a digit
    return ",00" not in digits and ",01" not in digits and ",-00" not in digits and ",-01" not in digits


_ONE_FOR_DIGITS = str.maketrans("23456789", "11111111")


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
