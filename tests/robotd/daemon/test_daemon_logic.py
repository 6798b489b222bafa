"""The daemon's control logic in-process, on a hand-driven clock: the deadman, a fresh command after the motors
reconnect, and a stalled wheel's fault in the status and the log (the wheels and the clock are fakes)."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest
from inprocess_daemon import AT_REST, Harness, daemon_config

from robotd.kinematics import Twist

FORWARD = Twist(0.1, 0.0, 0.0)


@pytest.fixture
def harness(tmp_path: Path) -> Harness:
    return Harness(daemon_config(tmp_path))


def test_the_motors_stop_one_period_after_the_deadman_timeout_when_commands_stop(harness: Harness) -> None:
    harness.encoders.speeds = [2.0, 2.0, 2.0, 2.0]  # the wheels turn: no stall
    for _ in range(10):
        harness.tick(send=FORWARD)
    last_sent = harness.clock.now
    assert harness.motors.duties != AT_REST
    deadman = harness.daemon.config.teleop.deadman_timeout_s
    driving_until = zero_at = None
    while harness.clock.now < last_sent + deadman + 5 * harness.period_s:
        if harness.tick() != AT_REST:
            driving_until = harness.clock.now
        elif zero_at is None:
            zero_at = harness.clock.now
    assert driving_until is not None
    assert zero_at is not None
    assert driving_until <= last_sent + deadman < zero_at <= last_sent + deadman + harness.period_s + 1e-9
    assert harness.status()["drivers"]["control"]["state"] == "deadman"


async def test_after_the_motors_reconnect_only_a_command_sent_afterwards_drives(harness: Harness) -> None:
    harness.encoders.speeds = [2.0, 2.0, 2.0, 2.0]
    for _ in range(5):
        harness.tick(send=FORWARD)
    lost = harness.motors
    lost.fail_next = True  # pigpiod goes away
    harness.tick()
    assert harness.daemon.motors is None
    assert lost.closed
    await harness.daemon._reconnect_motors()  # a real 0.2 s back-off sleep, then the fresh motor outputs
    assert harness.motors is not lost
    for _ in range(5):  # the fake clock stood still: the command from before the loss is within the deadman timeout
        assert harness.tick() == AT_REST
    assert harness.tick(send=FORWARD) != AT_REST


def test_a_stalled_wheel_stops_the_robot_and_the_status_and_log_say_so_until_a_fresh_command(
    harness: Harness, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="robotd")
    harness.encoders.speeds = [0.0, 2.13, 2.13, 2.13]  # the front-left encoder is dead; the others see their wheels
    for _ in range(round(5.0 / harness.period_s)):  # the client holds 0.1 m/s for 5 s
        harness.tick(send=FORWARD)
    control = harness.status()["drivers"]["control"]
    assert control["state"] == "fault"
    assert control["stall_faults"] == 1
    assert [(f["kind"], f["wheels"]) for f in control["faults"]] == [("stall", ["front_left"])]
    assert harness.motors.duties == AT_REST
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING and "front_left" in r.getMessage()]
    assert len(warnings) == 1, "one WARNING line when the fault latches, not one per period"
    # The operator lets go: still held, still reported.
    harness.tick(send=Twist(0.0, 0.0, 0.0))
    assert harness.status()["drivers"]["control"]["faults"] != []
    assert harness.motors.duties == AT_REST
    # A fresh command clears it (INFO) and drives again.
    assert harness.tick(send=FORWARD) != AT_REST
    assert harness.status()["drivers"]["control"]["faults"] == []
    assert any(r.levelno == logging.INFO and "stall fault cleared" in r.getMessage() for r in caplog.records)


def test_speeds_of_a_degraded_encoder_sample_are_unknown_not_zero_so_no_stall_is_blamed(harness: Harness) -> None:
    # The encoder stream is lost (pigpiod's notification socket gone): every sample is degraded and reads 0.
    for _ in range(round(5.0 / harness.period_s)):
        harness.tick(send=FORWARD, degraded=True)
    control = harness.status()["drivers"]["control"]
    assert control["faults"] == []
    assert control["state"] == "driving"
    feed_forward = harness.daemon.controller.last.wheel_setpoints[0] / 20.0
    assert harness.motors.duties[0] == pytest.approx(feed_forward), "open-loop at the feed-forward, no wind-up"
    # A sample degraded by a lost report while the stream runs still carries measured speeds: the PID uses them.
    harness.encoders.speeds = [0.5, 0.5, 0.5, 0.5]
    harness.tick(send=FORWARD, degraded=True)
    assert harness.motors.duties[0] > feed_forward, "closed loop: the slow wheel is pushed beyond the feed-forward"
