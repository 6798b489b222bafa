"""The sensor log's records as MCAP/Foxglove channels, derived from robotd.logs.events: one JSON channel per record
type, `/log/<type>`, whose messages are the log's own lines. Pure (no sink, no I/O).

Derived, not listed: every member of the `Record` union (its msgspec tag and its JSON schema) becomes a channel, so a
record type added to the log format flows into recordings, replays and the converter without an edit here. A
message's payload is exactly the line the JSON Lines log holds for the record, so converting either way is lossless.

Order. The log is in arrival order, which is not always the order of `t` (a fix's arrival can come between two
wheel samples stamped earlier). `LogClock` stamps each record's log time from its `t` but strictly after the one
before, so that reading a file's `/log/*` messages in log-time order gives back the log's order exactly.
"""

from __future__ import annotations

import math
import typing
from dataclasses import dataclass
from typing import Any

import msgspec

from robotd.logs import events

TOPIC_PREFIX = "/log/"
ENCODING = "json"


@dataclass(frozen=True, slots=True)
class RecordTopic:
    """One record type's channel: its topic, schema name and JSON schema."""

    tag: str
    topic: str
    schema_name: str
    schema: dict[str, Any]


def record_types() -> dict[str, type[msgspec.Struct]]:
    """Every record type of the log format by its tag (the line's "type"), from the `Record` union."""
    found: dict[str, type[msgspec.Struct]] = {}
    for cls in typing.get_args(events.Record):
        tag = cls.__struct_config__.tag
        if isinstance(tag, str):
            found[tag] = cls
    return found


def record_topics() -> dict[str, RecordTopic]:
    """Every record type's channel by its tag."""
    types = record_types()
    _, components = msgspec.json.schema_components(list(types.values()))
    topics: dict[str, RecordTopic] = {}
    for tag, cls in types.items():
        schema = _finite(components[cls.__name__])
        schema.setdefault("title", cls.__name__)
        topics[tag] = RecordTopic(tag, TOPIC_PREFIX + tag, f"robotd.log.{tag}", schema)
    return topics


def _finite(schema: Any) -> Any:
    """The schema without non-finite defaults (NaN means "absent" in a record; JSON has no NaN)."""
    if isinstance(schema, dict):
        return {
            key: _finite(value)
            for key, value in schema.items()
            if not (key == "default" and isinstance(value, float) and not math.isfinite(value))
        }
    if isinstance(schema, list):
        return [_finite(value) for value in schema]
    return schema


def tag_of(record: events.Record) -> str:
    """A record's tag (its line's "type")."""
    tag = type(record).__struct_config__.tag
    assert isinstance(tag, str)  # every record type is tagged (record_types)
    return tag


def payload(record: events.Record) -> bytes:
    """The record's message: its JSON Lines line, without the newline."""
    return events.encode(record).encode()


class LogClock:
    """Log times (ns) for records, from their time `t` (s) on the log's clock plus `offset_ns`, strictly increasing."""

    def __init__(self, offset_ns: int = 0) -> None:
        self.offset_ns = offset_ns
        self._last = -1

    def at(self, t: float) -> int:
        """The log time of a published message at t (not sequenced: poses, plots)."""
        return max(0, self.offset_ns + round(t * 1e9))

    def next_record(self, record: events.Record) -> int:
        """The log time of the next record: from its `t` (the meta line has none), after the record before."""
        t = getattr(record, "t", None)
        stamp = self.at(t) if isinstance(t, float) else 0
        self._last = max(stamp, self._last + 1)
        return self._last
