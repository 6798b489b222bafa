"""The sensor log in an MCAP file: read (with the `mcap` package) and written (with the SDK's MCAP writer), so that
JSON Lines and MCAP are both first-class, and converted either way without loss.

The log is the file's `/log/<type>` channels (robotd.viz.logtopics): each message is one JSON Lines line, and log
times increase strictly in the log's order, so reading them in log-time order gives back the JSON Lines file. The
other channels (what the daemon published: poses, fixes, plots) are for viewing and are not part of the log.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable
from pathlib import Path

import foxglove
from mcap.exceptions import McapError
from mcap.reader import make_reader

from robotd.logs import events
from robotd.logs.sensorlog import LogWriter, SensorLog, parse_lines, read_log
from robotd.viz.channels import Channels
from robotd.viz.logtopics import TOPIC_PREFIX, LogClock

MCAP_SUFFIX = ".mcap"


class McapLogError(OSError):
    """An MCAP file that cannot be read as one (one line, for the operator)."""


def is_mcap(path: str | Path) -> bool:
    """Whether the path names an MCAP file (by its suffix)."""
    return Path(path).suffix == MCAP_SUFFIX


def log_lines(path: str | Path) -> list[bytes]:
    """The `/log/*` messages of an MCAP file in the log's order: the lines of its sensor log."""
    try:
        with Path(path).open("rb") as stream:
            reader = make_reader(stream)
            summary = reader.get_summary()
            if summary is None:  # no summary (a file cut short): every message is read and the log's ones kept
                messages = reader.iter_messages(log_time_order=True)
            else:
                topics = [c.topic for c in summary.channels.values() if c.topic.startswith(TOPIC_PREFIX)]
                messages = reader.iter_messages(topics=topics, log_time_order=True)
            return [message.data for _, channel, message in messages if channel.topic.startswith(TOPIC_PREFIX)]
    except (McapError, EOFError, ValueError, KeyError, struct.error) as error:
        raise McapLogError(f"not a readable MCAP file: {error}") from None


def read_mcap_log(path: str | Path) -> SensorLog:
    """The sensor log of an MCAP file, parsed as `robotd.logs.sensorlog.read_log` parses a JSON Lines one (a bad
    message is reported by its number among the log's messages and skipped)."""
    return parse_lines(log_lines(path))


def read_any_log(path: str | Path) -> SensorLog:
    """A sensor log from a JSON Lines file or an MCAP file (by the suffix)."""
    return read_mcap_log(path) if is_mcap(path) else read_log(path)


def write_mcap_log(records: Iterable[events.Record], path: str | Path) -> int:
    """An MCAP file holding these records on their `/log/*` channels (an existing file is replaced); returns how many
    were written."""
    context = foxglove.Context()
    channels = Channels(context)
    clock = LogClock()
    count = 0
    with foxglove.open_mcap(path, allow_overwrite=True, context=context):
        for record in records:
            channels.record(record, clock.next_record(record))
            count += 1
    return count


def convert(source: str | Path, target: str | Path) -> tuple[SensorLog, int]:
    """JSON Lines -> MCAP or MCAP -> JSON Lines, by the suffixes; returns the log read and the events written."""
    log = read_any_log(source)
    if is_mcap(target):
        return log, write_mcap_log([log.meta, *log.events], target) - 1
    with Path(target).open("w", encoding="utf-8") as stream:
        writer = LogWriter(stream, log.meta)
        for event in log.events:
            writer.write(event)
    return log, len(log.events)
