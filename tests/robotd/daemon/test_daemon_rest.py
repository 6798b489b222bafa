"""A robot at rest costs almost nothing: the control loop wakes only for the deadman's heartbeat, the pose loop not at
all without a client; a command wakes the loop at once and it steps at its rate again.

Counts over an idle interval with generous bounds (a busy machine only makes the loops wake less), never timing.
"""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import pytest
from inprocess_daemon import FakeEncoders, FakeMotors, daemon_config, running, until

from robotd.daemon.pacer import REST_BUMPS_PER_TIMEOUT, ControlPacer
from robotd.daemon.service import Daemon
from robotd.daemon.teleop import TeleopCommand
from robotd.kinematics import Twist


def test_at_rest_the_heartbeat_comes_several_times_per_deadman_timeout() -> None:
    pacer = ControlPacer(period_s=0.02, deadman_timeout_s=0.5)
    assert pacer.rest_period_s == 0.5 / REST_BUMPS_PER_TIMEOUT
    assert REST_BUMPS_PER_TIMEOUT >= 3  # a late wake-up or two must not trip the deadman of a parked robot
    assert ControlPacer(period_s=0.02, deadman_timeout_s=0.04).rest_period_s == 0.02  # never faster than the period


async def test_at_rest_the_loops_hardly_wake_and_a_command_wakes_the_control_loop(tmp_path: Path) -> None:
    motors = FakeMotors()
    daemon = Daemon(
        daemon_config(tmp_path),
        encoders=FakeEncoders(time.monotonic),
        clock=time.monotonic,
        motors_factory=lambda: motors,
    )
    idle_s = 1.0
    async with running(daemon):
        await until(lambda: daemon.motors is not None and daemon.pacer.rest_wakeups > 0, "the daemon at rest")
        steps, published = daemon._counters["control_steps"], daemon.pose_server.counters["published"]
        await asyncio.sleep(idle_s)
        rest_steps = daemon._counters["control_steps"] - steps
        # stepping at 50 Hz would take 50 steps; at rest only the heartbeat wakes the loop (8 a second here)
        assert rest_steps <= idle_s / daemon.pacer.rest_period_s + 3, rest_steps
        assert daemon.pose_server.counters["published"] == published  # nobody listens: no pose is built
        assert daemon.control_periods.summary()["ticks"] == 0  # a parked robot's heartbeat is not a control period

        wakeups = daemon.pacer.rest_wakeups
        for sequence in range(1, 11):  # a client commanding at 20 Hz for half a second
            daemon._on_teleop(TeleopCommand(Twist(0.2, 0.0, 0.0), 1, sequence, time.monotonic()))
            await asyncio.sleep(0.05)
        assert any(motors.duties)
        # the loop left its rest at the first command (one more rest wake-up at most) and ticked at its period since
        # (about 25 ticks in the half second; the commands' own steps are not ticks)
        assert daemon.pacer.rest_wakeups <= wakeups + 1
        ticks = daemon.control_periods.summary()["ticks"]
        assert ticks > 10, ticks


@pytest.mark.parametrize("steps_between", [0, 1, 2, 3])
async def test_a_loop_at_rest_cancelled_as_a_command_arrives_ends(steps_between: int) -> None:
    """A command and the shutdown at the same moment: the cancellation must not be lost (the daemon's TaskGroup
    would wait for the control loop forever)."""
    pacer = ControlPacer(period_s=0.02, deadman_timeout_s=0.5)

    async def control_loop() -> None:
        while True:
            await pacer.next_step(at_rest=True)

    loop = asyncio.create_task(control_loop())
    await asyncio.sleep(0)  # the loop waits for a command
    pacer.command_arrived()
    for _ in range(steps_between):
        await asyncio.sleep(0)
    loop.cancel()
    with pytest.raises(asyncio.CancelledError):
        async with asyncio.timeout(5.0):  # a lost cancellation: the loop runs on and this times out instead
            await loop
