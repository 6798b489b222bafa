"""Signed fleet orders, checked sans-I/O: genuine, forged, tampered, replayed, misdirected, and the hold."""

from __future__ import annotations

import json

import pytest

from robotd.fleet import topics
from robotd.fleet.orders import Action, OrderCheck, StopHold, sign

KEY = b"the-fleet-key-0123456789abcdef"
NOW_S = 1_800_000_000.0
T0 = int(NOW_S * 1e9)


def check(robot_id: str = "r1") -> OrderCheck:
    return OrderCheck(KEY, robot_id, max_clock_offset_s=30.0)


def test_a_genuine_stop_is_accepted() -> None:
    orders = check()
    order = orders.check(topics.FLEET_STOP, sign(KEY, Action.STOP, topics.FLEET, T0, "ops"), NOW_S)
    assert order is not None
    assert (order.action, order.target, order.time_ns, order.issuer) == (Action.STOP, "fleet", T0, "ops")
    assert orders.counters()["accepted"] == 1


@pytest.mark.parametrize(
    ("payload", "reason"),
    [
        (sign(b"another-key-of-sufficient-length", Action.STOP, "fleet", T0, "ops"), "bad_tag"),
        (sign(KEY, Action.STOP, "fleet", T0, "ops").replace(b'"stop"', b'"release"'), "bad_tag"),
        (sign(KEY, Action.STOP, "fleet", T0, "ops").replace(b'"ops"', b'"eve"'), "bad_tag"),
        (json.dumps({"v": 1, "action": "stop", "target": "fleet", "time_ns": T0}).encode(), "unauthenticated"),
        (b"stop", "malformed"),
        (b"\xff\xfe", "malformed"),
        (json.dumps({"v": 2, "action": "stop", "target": "fleet", "time_ns": T0, "tag": "00"}).encode(), "malformed"),
        (json.dumps({"v": 1, "action": "halt", "target": "fleet", "time_ns": T0, "tag": "00"}).encode(), "malformed"),
        (json.dumps({"v": 1, "action": "stop", "target": "fleet", "time_ns": 1.5, "tag": "00"}).encode(), "malformed"),
        (b"x" * 2000, "malformed"),
        (sign(KEY, Action.STOP, "fleet", T0 + 31 * 10**9, "ops"), "clock_offset"),
    ],
    ids=["other key", "action changed", "issuer changed", "no tag", "not json", "not utf8", "version", "action",
         "time type", "too long", "future"],
)  # fmt: skip
def test_a_bad_order_is_refused_and_counted(payload: bytes, reason: str) -> None:
    orders = check()
    assert orders.check(topics.FLEET_STOP, payload, NOW_S) is None
    assert orders.counters()[reason] == 1
    assert orders.counters()["accepted"] == 0


def test_an_order_for_another_robot_or_topic_is_refused() -> None:
    orders = check("r1")
    for_r2 = sign(KEY, Action.RELEASE, "r2", T0, "ops")
    assert orders.check(topics.stop("r1"), for_r2, NOW_S) is None  # replayed onto our topic
    assert orders.check(topics.FLEET_STOP, for_r2, NOW_S) is None  # onto the fleet's
    fleet_order = sign(KEY, Action.RELEASE, "fleet", T0, "ops")
    assert orders.check(topics.stop("r1"), fleet_order, NOW_S) is None
    assert orders.counters()["wrong_target"] == 3


def test_replays_are_refused_and_repeats_ignored() -> None:
    orders = check()
    stop = sign(KEY, Action.STOP, "fleet", T0, "ops")
    release = sign(KEY, Action.RELEASE, "fleet", T0 + 1, "ops")
    assert orders.check(topics.FLEET_STOP, stop, NOW_S) is not None
    assert orders.check(topics.FLEET_STOP, stop, NOW_S) is None  # delivered again on resubscription: a repeat
    assert orders.check(topics.FLEET_STOP, release, NOW_S) is not None
    assert orders.check(topics.FLEET_STOP, stop, NOW_S) is None  # the old stop after the release: a replay
    assert orders.check(topics.FLEET_STOP, sign(KEY, Action.STOP, "fleet", T0 + 2, "ops"), NOW_S) is not None
    assert orders.check(topics.FLEET_STOP, release, NOW_S) is None  # the old release after a new stop
    counts = orders.counters()
    assert (counts["accepted"], counts["repeats"], counts["replayed"]) == (3, 1, 2)


def test_targets_are_ordered_separately() -> None:
    orders = check()
    assert orders.check(topics.stop("r1"), sign(KEY, Action.STOP, "r1", T0 + 5, "ops"), NOW_S) is not None
    assert orders.check(topics.FLEET_STOP, sign(KEY, Action.STOP, "fleet", T0, "ops"), NOW_S) is not None


def test_an_empty_payload_is_a_deletion_that_releases_nothing() -> None:
    orders = check()
    assert orders.check(topics.FLEET_STOP, b"", NOW_S) is None
    assert orders.counters()["cleared"] == 1


def test_the_hold_lasts_until_every_stop_is_released() -> None:
    orders, hold = check(), StopHold()
    fleet_stop = orders.check(topics.FLEET_STOP, sign(KEY, Action.STOP, "fleet", T0, "ops"), NOW_S)
    own_stop = orders.check(topics.stop("r1"), sign(KEY, Action.STOP, "r1", T0, "ops"), NOW_S)
    fleet_release = orders.check(topics.FLEET_STOP, sign(KEY, Action.RELEASE, "fleet", T0 + 1, "ops"), NOW_S)
    own_release = orders.check(topics.stop("r1"), sign(KEY, Action.RELEASE, "r1", T0 + 1, "ops"), NOW_S)
    assert fleet_stop is not None
    assert own_stop is not None
    assert fleet_release is not None
    assert own_release is not None
    assert hold.apply(fleet_stop) is True
    assert hold.apply(own_stop) is False  # already held
    assert hold.apply(fleet_release) is False  # the robot's own stop still holds it
    assert hold.held
    assert [stop["target"] for stop in hold.describe()["stops"]] == ["r1"]
    assert hold.apply(own_release) is True
    assert not hold.held
