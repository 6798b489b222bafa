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

import re
from dataclasses import dataclass

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
        counts = np.array(list(map(int, tokens)), dtype=np.int64)
    except (ValueError, OverflowError):
        return None
    return t, counts.reshape(-1, 4)


def _numbers_text(template: Template, lines: list[str]) -> str | None:
    """',n1,n2,...,' : every line's numbers in order, if every line has exactly the template's shape."""
    if not lines:
        return None
    block = "\n".join(lines)
    if any(chr(c) in block for c in (1, 2, 3, 4, 5, 0x1F)):  # the markers must not occur in the text itself
        return None
    # markers: \x01 the prefix, \x02.. the distinct separators in order, \x1f the suffix; longest first, as the
    # type-bearing separator starts with the same ", " as the others
    distinct = sorted(set(template.separators), key=len, reverse=True)
    code = {sep: chr(2 + i) for i, sep in enumerate(distinct)}
    for sep in distinct:
        block = block.replace(sep, code[sep])
    block = block.replace(PREFIX, "\x01").replace(template.suffix, "\x1f")
    expected = "\x01" + "".join(code[sep] for sep in template.separators) + "\x1f"
    if block.translate(_DELETE_NUMBERS) != "\n".join([expected] * len(lines)):
        return None
    table: dict[int, str | None] = {ord(c): "," for c in code.values()}
    table.update({1: ",", 0x1F: None, ord("\n"): None})
    text = block.translate(table) + ","
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
    return _LEADING_ZERO.search(text) is None


_LEADING_ZERO = re.compile(r",-?0[0-9]")


__all__ = ["IPS", "TEMPLATES", "TRUTH", "WHEELS", "Template", "parse_batch", "parse_wheels"]
