"""The heartbeat deadman's state machine on a fake clock: armed by the first heartbeat, tripped once at the deadline
and not a moment before, re-armed by the next heartbeat, disarmed on request, never armed without a timeout."""

from __future__ import annotations

import pytest

from drivers.gpiod.heartbeat import CLOSING, DISARM, HEARTBEAT, Guard, HeartbeatMonitor


def test_nothing_is_guarded_before_the_first_heartbeat() -> None:
    monitor = HeartbeatMonitor(0.5)
    assert monitor.wait_s(100.0) is None
    assert not monitor.expired(1e9)
    assert (monitor.state, monitor.trips) == (Guard.DISARMED, 0)


def test_the_trip_comes_exactly_at_the_timeout_after_the_last_heartbeat_and_only_once() -> None:
    monitor = HeartbeatMonitor(0.5)
    monitor.feed(HEARTBEAT, 10.0)
    monitor.feed(HEARTBEAT * 3, 10.02)  # a read that found three heartbeats: the time of the read counts
    assert monitor.wait_s(10.3) == pytest.approx(0.22)
    assert not monitor.expired(10.519)
    assert monitor.expired(10.52)
    assert (monitor.state, monitor.trips) == (Guard.TRIPPED, 1)
    assert not monitor.expired(11.0)  # once per trip
    assert monitor.wait_s(11.0) is None  # nothing to wait for until a heartbeat comes


def test_a_heartbeat_after_a_trip_re_arms_it_as_pigpios_script_does() -> None:
    monitor = HeartbeatMonitor(0.2)
    monitor.feed(HEARTBEAT, 0.0)
    assert monitor.expired(0.2)
    monitor.feed(HEARTBEAT, 5.0)  # the owner resumed after SIGSTOP
    assert monitor.state is Guard.ARMED
    assert not monitor.expired(5.1)
    assert monitor.expired(5.2)
    assert monitor.trips == 2


def test_disarm_leaves_only_death_guarded_until_the_next_heartbeat() -> None:
    monitor = HeartbeatMonitor(0.2)
    monitor.feed(HEARTBEAT + DISARM, 0.0)
    assert not monitor.expired(10.0)
    monitor.feed(HEARTBEAT, 10.0)
    assert monitor.expired(10.2)


def test_without_a_timeout_heartbeats_arm_nothing_and_closing_is_remembered() -> None:
    monitor = HeartbeatMonitor(None)
    monitor.feed(HEARTBEAT * 5 + b"x", 0.0)  # an unknown byte is ignored
    assert (monitor.state, monitor.wait_s(0.0), monitor.expired(100.0)) == (Guard.DISARMED, None, False)
    assert not monitor.closing
    monitor.feed(CLOSING, 1.0)
    assert monitor.closing
