"""Fleet stop and release orders: signed with the fleet key, checked sans-I/O, held until released.

Theory of operation. An order is a small JSON object published retained on `robotd/fleet/stop` (every robot) or
`robotd/<robot_id>/stop` (one robot): `{"v": 1, "action": "stop"|"release", "target": ..., "time_ns": ...,
"issuer": ..., "tag": ...}`, where `tag` is the hex HMAC-SHA256, with the fleet key, of the version, action, target,
time and issuer (`signed_bytes`). The target is signed and must match the topic, so an order for one robot cannot be
replayed on another's topic or on the fleet's. As for teleop, the tag is checked before anything else moves.

Replays. Retained orders are delivered again on every (re)subscription, so a copy of the order last accepted on a
topic is a repeat, not an attack: it is ignored and counted as `repeats`. Any other order must be signed later
(`time_ns`) than the last accepted for its target, else it is refused as `replayed`: an old release republished
after a new stop never releases it, an old stop republished after a release is refused too (and counted). An order
signed more than `max_clock_offset_s` ahead of our clock is refused (`clock_offset`): accepted, it would lock out every
later order of a person whose clock is right. An order is not refused for being old: a stop retained for hours must
still stop a robot that boots now.

The hold. A robot is held stopped while the fleet target or its own target has an accepted stop newer than that
target's last release. A retained order deleted from the broker (an empty payload) releases nothing: only a signed
release does. What this cannot do: anyone with the fleet key can release every robot (each robot holds the key to
verify orders), so the broker's ACLs must let only the operators write the stop topics (see the README's Fleets
section); a robot that restarts forgets the orders it saw and obeys whatever is retained on the broker.
"""

from __future__ import annotations

import enum
import hmac
import json
import math
from collections import Counter
from dataclasses import dataclass
from typing import Any

from robotd.fleet import topics

VERSION = 1
MAX_ORDER_BYTES = 1024
MAX_ISSUER_CHARS = 128


class Action(enum.Enum):
    """What an order asks."""

    STOP = "stop"
    RELEASE = "release"


class Refusal(enum.Enum):
    """Why an order was refused; each has a counter."""

    MALFORMED = "malformed"  # not JSON, missing or mistyped fields, too long, another version
    UNAUTHENTICATED = "unauthenticated"  # no tag
    BAD_TAG = "bad_tag"  # the tag does not verify with the fleet key (forged, or another key)
    WRONG_TARGET = "wrong_target"  # the signed target is not the topic's
    CLOCK_OFFSET = "clock_offset"  # signed more than max_clock_offset_s in our future
    REPLAYED = "replayed"  # not later than the last order accepted for its target


@dataclass(frozen=True, slots=True)
class Order:
    """A verified stop or release for `target` (a robot id or topics.FLEET), signed at `time_ns` (Unix ns)."""

    action: Action
    target: str
    time_ns: int
    issuer: str


def signed_bytes(action: Action, target: str, time_ns: int, issuer: str) -> bytes:
    """What the tag covers: every field but the tag, one per line."""
    return f"robotd-fleet-order\n{VERSION}\n{action.value}\n{target}\n{time_ns}\n{issuer}".encode()


def sign(key: bytes, action: Action, target: str, time_ns: int, issuer: str) -> bytes:
    """The payload of a signed order (UTF-8 JSON)."""
    tag = hmac.digest(key, signed_bytes(action, target, time_ns, issuer), "sha256").hex()
    order = {"v": VERSION, "action": action.value, "target": target, "time_ns": time_ns, "issuer": issuer, "tag": tag}
    return json.dumps(order, separators=(",", ":")).encode()


def _fields(payload: bytes) -> tuple[Action, str, int, str, str] | None:
    """(action, target, time_ns, issuer, tag) of a well-formed order, else None."""
    if len(payload) > MAX_ORDER_BYTES:
        return None
    try:
        raw: Any = json.loads(payload)
    except (ValueError, UnicodeDecodeError):
        return None
    if not isinstance(raw, dict) or raw.get("v") != VERSION:
        return None
    action, target, time_ns = raw.get("action"), raw.get("target"), raw.get("time_ns")
    issuer, tag = raw.get("issuer", ""), raw.get("tag", "")
    if action not in ("stop", "release") or not isinstance(target, str) or not isinstance(issuer, str):
        return None
    if not isinstance(time_ns, int) or isinstance(time_ns, bool) or time_ns <= 0 or not isinstance(tag, str):
        return None
    if len(issuer) > MAX_ISSUER_CHARS:
        return None
    return Action(action), target, time_ns, issuer, tag


class OrderCheck:
    """Verifies orders for one robot (sans-I/O: topic, payload and our Unix time in; an Order or None out)."""

    def __init__(self, key: bytes, robot_id: str, max_clock_offset_s: float = 30.0) -> None:
        self.key = key
        self.robot_id = robot_id
        self.max_clock_offset_ns = int(max_clock_offset_s * 1e9)
        self.refused: Counter[Refusal] = Counter()
        self.accepted = 0
        self.repeats = 0  # the last accepted order delivered again (a retained message on resubscription)
        self.cleared = 0  # a retained order deleted (empty payload): releases nothing
        self._last: dict[str, tuple[int, str]] = {}  # target -> (time_ns, tag) of the last accepted order

    def counters(self) -> dict[str, int]:
        """Accepted, repeated, cleared and refused orders, by reason (every reason present)."""
        counts = {"accepted": self.accepted, "repeats": self.repeats, "cleared": self.cleared}
        return counts | {reason.value: self.refused[reason] for reason in Refusal}

    def topics(self) -> tuple[str, str]:
        """The stop topics this robot obeys."""
        return topics.FLEET_STOP, topics.stop(self.robot_id)

    def check(self, topic: str, payload: bytes, wall_time: float) -> Order | None:
        """The order on `topic` if it is genuine, new and for us; else None, counted by why."""
        if not payload:
            self.cleared += 1
            return None
        outcome = self._check(topic, payload, wall_time)
        if isinstance(outcome, Refusal):
            self.refused[outcome] += 1
            return None
        return outcome

    def _check(self, topic: str, payload: bytes, wall_time: float) -> Order | Refusal | None:
        fields = _fields(payload)
        if fields is None:
            return Refusal.MALFORMED
        action, target, time_ns, issuer, tag = fields
        if not tag:
            return Refusal.UNAUTHENTICATED
        expected = hmac.digest(self.key, signed_bytes(action, target, time_ns, issuer), "sha256").hex()
        if not hmac.compare_digest(tag, expected):
            return Refusal.BAD_TAG
        if topic not in self.topics() or topic != topics.stop(target):
            return Refusal.WRONG_TARGET
        last_time, last_tag = self._last.get(target, (0, ""))
        if tag == last_tag:
            self.repeats += 1
            return None
        if time_ns <= last_time:
            return Refusal.REPLAYED
        if math.isfinite(wall_time) and time_ns - int(wall_time * 1e9) > self.max_clock_offset_ns:
            return Refusal.CLOCK_OFFSET
        self._last[target] = (time_ns, tag)
        self.accepted += 1
        return Order(action, target, time_ns, issuer)


class StopHold:
    """Which targets hold this robot stopped (the fleet's, its own, or both)."""

    def __init__(self) -> None:
        self._stops: dict[str, Order] = {}

    @property
    def held(self) -> bool:
        """Whether a stop is in force."""
        return bool(self._stops)

    def apply(self, order: Order) -> bool:
        """Take an accepted order; True when the robot went from free to held or back."""
        before = self.held
        if order.action is Action.STOP:
            self._stops[order.target] = order
        else:
            self._stops.pop(order.target, None)
        return before != self.held

    def describe(self) -> dict[str, Any]:
        """For the status: held or not, and each stop in force with who signed it and when (Unix s)."""
        stops = [
            {"target": order.target, "issuer": order.issuer, "time": order.time_ns / 1e9}
            for order in self._stops.values()
        ]
        return {"held": self.held, "stops": stops}
