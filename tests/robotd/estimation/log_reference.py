"""The reference for the bulk log reader: every line through the per-line reader (json.loads), one at a time."""

from __future__ import annotations

from robotd import logfile
from robotd.logfile import SensorLog, Wheels


def reference_lines(lines: list[str]) -> SensorLog:
    """The plain reader: every line through the per-line reader (json.loads), ticks checked to fit an int64."""
    log = SensorLog()
    for number, line in enumerate(lines, start=1):
        try:
            item = logfile._parse_line(line)
            if isinstance(item, Wheels) and not all(-(2**63) <= n < 2**63 for n in item.ticks):
                raise ValueError("'ticks' must be 64-bit integers")
        except ValueError as error:
            log.problems.append(f"line {number}: {error}")
            continue
        if isinstance(item, str):
            log.unknown_types[item] += 1
        elif isinstance(item, logfile.Meta):
            log.meta = item
        elif item is not None:
            log.events.append(item)
    return log
