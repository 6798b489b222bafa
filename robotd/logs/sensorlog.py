"""The sensor log format (JSON Lines): the interchange for record, replay and evaluation.

One JSON object a line, in arrival order; `t` is the arrival time in seconds on one monotonic clock. The format is
specified in the README ("Sensor log format"); its records are robotd.logs.events'. Reading never raises on content:
each line is decoded on its own (msgspec, into the tagged union of the records), a malformed line is reported with
its line number and the reason and skipped, an unknown `type` is counted, so that a log from a newer robotd or a
damaged file still replays everything it can.
"""

from __future__ import annotations

import re
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

import msgspec

from robotd.logs.events import (
    FORMAT,
    TYPES,
    VERSION,
    Command,
    Event,
    IpsFix,
    IpsLost,
    Meta,
    Record,
    Truth,
    TwistSample,
    Wheels,
    encode,
)


class LogWriter:
    """Writes a sensor log: the meta line first, then one line per event, flushed as it goes."""

    def __init__(self, stream: TextIO, meta: Meta) -> None:
        self._stream = stream
        self._stream.write(encode(meta) + "\n")

    def write(self, event: Event) -> None:
        """Append one event."""
        self._stream.write(encode(event) + "\n")

    def flush(self) -> None:
        """Push buffered lines to the file."""
        self._stream.flush()


@dataclass(slots=True)
class SensorLog:
    """A parsed log: its meta, its events in file order, and what could not be used."""

    meta: Meta = field(default_factory=Meta)
    events: list[Event] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)  # "line N: reason", one per malformed line
    unknown_types: Counter[str] = field(default_factory=Counter)
    lines: list[int] = field(default_factory=list)  # each event's line number in the file (from 1), when read from one


class _Typed(msgspec.Struct):
    """Any object with a string `type` (a line that is not one of the records: is it of an unknown type?)."""

    type: str


_decoder = msgspec.json.Decoder(Record)
_typed = msgspec.json.Decoder(_Typed)


def parse_lines(lines: Iterable[str | bytes]) -> SensorLog:
    """Parse the lines of a sensor log (without their line ends, or with them); never raises on content."""
    log = SensorLog()
    decode = _decoder.decode
    events, numbers = log.events, log.lines
    for number, line in enumerate(lines, start=1):
        try:
            record = decode(line)
        except (msgspec.DecodeError, RecursionError, UnicodeError) as error:
            # (RecursionError: nested beyond the decoder's depth; UnicodeError: a str that is not valid Unicode)
            if line.strip():
                kind = _unknown_type(line, error)
                if kind is None:
                    log.problems.append(f"line {number}: {_reason(error, line)}")
                else:
                    log.unknown_types[kind] += 1
            continue
        if isinstance(record, Meta):  # (msgspec >= 0.23 types the decoded union: isinstance narrows it)
            log.meta = record
        else:
            events.append(record)
            numbers.append(number)
    return log


def _unknown_type(line: str | bytes, error: Exception) -> str | None:
    """The type of a line that is an object of a type this version does not know, else None."""
    if not (isinstance(error, msgspec.ValidationError) and str(error).endswith("at `$.type`")):
        return None
    try:
        kind = _typed.decode(line).type
    except (msgspec.DecodeError, RecursionError):
        return None
    return kind if kind not in TYPES else None


_NON_FINITE = re.compile(rb"[-:\[,\s](Infinity|NaN)\b")


def _reason(error: Exception, line: str | bytes) -> str:
    """The decoder's reason, in words."""
    if isinstance(error, RecursionError):
        return "nested too deeply"
    if isinstance(error, UnicodeError):
        return "not valid Unicode"
    text = str(error)
    raw = line.encode("utf-8", "replace") if isinstance(line, str) else line
    if "invalid character" in text and _NON_FINITE.search(raw):
        # Python's json writes these for inf and nan; JSON has no such numbers, and no sensor measures them
        return f"a number that is not finite (Infinity or NaN): {text}"
    if "out of range" in text:
        return f"{text} (a number beyond any double or 64-bit integer)"
    return text


def read_log(path: str | Path) -> SensorLog:
    """Read a sensor log file ('\\r\\n' and a lone '\\r' end a line too, as in a text-mode read)."""
    data = Path(path).read_bytes()
    if b"\r" in data:
        data = data.replace(b"\r\n", b"\n").replace(b"\r", b"\n")
    lines = data.split(b"\n")
    if lines and not lines[-1]:
        lines.pop()  # the last line's end
    return parse_lines(lines)


__all__ = [
    "FORMAT",
    "VERSION",
    "Command",
    "Event",
    "IpsFix",
    "IpsLost",
    "LogWriter",
    "Meta",
    "SensorLog",
    "Truth",
    "TwistSample",
    "Wheels",
    "encode",
    "parse_lines",
    "read_log",
]
