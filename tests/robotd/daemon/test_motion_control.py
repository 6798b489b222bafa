"""The motion control loop, driven by a hand-driven clock: deadman, limits, slew, feed-forward, PID, anti-windup."""

from __future__ import annotations

import itertools
import math

import pytest

from robotd.config.model import ControlConfig, TeleopConfig
from robotd.daemon.control import ControlState, MotionController, Wheels
from robotd.kinematics import Geometry, Twist, forward, inverse

GEOMETRY = Geometry()
AT_REST: Wheels = (0.0, 0.0, 0.0, 0.0)


def controller(**control: float) -> MotionController:
    """A controller whose stall guard waits its longest (5 s): most tests here feed wheels at rest as a don't-care
    measurement while they look at the set-points; the guard has its own tests (test_stall_guard.py)."""
    return MotionController(GEOMETRY, ControlConfig(**{"stall_timeout_s": 5.0, **control}), TeleopConfig())


class Plant:
    """A first-order wheel: speed follows duty * top speed with a time constant, minus a constant drag."""

    def __init__(self, top_speed: float, tau: float = 0.05, drag: float = 0.0) -> None:
        self.speeds = [0.0, 0.0, 0.0, 0.0]
        self.top_speed, self.tau, self.drag = top_speed, tau, drag

    def advance(self, duties: Wheels, dt: float) -> Wheels:
        for i, duty in enumerate(duties):
            target = duty * self.top_speed - math.copysign(self.drag, duty) * (duty != 0.0)
            self.speeds[i] += (target - self.speeds[i]) * min(1.0, dt / self.tau)
        a, b, c, d = self.speeds
        return (a, b, c, d)


def test_deadman_zeroes_the_motors_within_the_timeout_plus_one_period() -> None:
    motion = controller()
    period, timeout = motion.period_s, motion.teleop.deadman_timeout_s
    command, sent_at = Twist(0.4, 0.0, 0.0), 10.0
    now, measured, last_nonzero = sent_at, AT_REST, None
    while now < sent_at + timeout + 3 * period:
        duties = motion.step(now, command, sent_at, measured)
        if any(d != 0.0 for d in duties):
            last_nonzero = now
        measured = (5.0, 5.0, 5.0, 5.0)  # the wheels are turning when the client goes silent
        now += period
    assert last_nonzero is not None, "the controller never drove the motors"
    assert last_nonzero <= sent_at + timeout
    zero_at = last_nonzero + period
    assert zero_at <= sent_at + timeout + period
    assert motion.last.duties == (0.0, 0.0, 0.0, 0.0)
    assert motion.last.state is ControlState.DEADMAN


def test_deadman_duties_are_exactly_zero_and_driving_restarts_from_rest() -> None:
    motion = controller()
    for i in range(30):
        motion.step(i * 0.02, Twist(0.5, 0.0, 0.0), i * 0.02, AT_REST)
    assert motion.last.setpoint.vx > 0.3
    assert motion.step(2.0, Twist(0.5, 0.0, 0.0), 0.58, (9.0, 9.0, 9.0, 9.0)) == (0.0, 0.0, 0.0, 0.0)
    # A fresh command after the deadman ramps up from standstill, not back to the old speed.
    motion.step(2.02, Twist(0.5, 0.0, 0.0), 2.02, AT_REST)
    assert motion.last.setpoint.vx == pytest.approx(motion.teleop.max_linear_accel_mps2 * motion.period_s)


def test_no_command_ever_and_non_finite_commands_keep_the_motors_off() -> None:
    motion = controller()
    assert motion.step(0.0, None, None, AT_REST) == (0.0, 0.0, 0.0, 0.0)
    assert motion.step(0.02, Twist(math.nan, 0.0, 0.0), 0.02, AT_REST) == (0.0, 0.0, 0.0, 0.0)
    assert motion.last.state is ControlState.DEADMAN


def test_speed_limits_and_slew_limits_shape_the_set_point() -> None:
    motion = controller(wheel_max_speed_rad_s=40.0)  # fast wheels: the teleop limits bind, not the wheels
    period, accel = motion.period_s, motion.teleop.max_linear_accel_mps2
    setpoints = []
    for i in range(100):
        now = i * period
        motion.step(now, Twist(5.0, -5.0, 0.0), now, AT_REST)
        setpoints.append(motion.last.setpoint)
    for before, after in itertools.pairwise(setpoints):
        assert abs(after.vx - before.vx) <= accel * period + 1e-12
    assert setpoints[-1].vx == pytest.approx(motion.teleop.max_vx_mps)
    assert setpoints[-1].vy == pytest.approx(-motion.teleop.max_vy_mps)


def test_a_command_beyond_the_wheels_top_speed_is_scaled_keeping_its_direction() -> None:
    motion = controller(wheel_max_speed_rad_s=10.0)
    for i in range(200):
        motion.step(i * 0.02, Twist(0.6, 0.6, 2.0), i * 0.02, AT_REST)
    final = motion.last.setpoint
    assert max(abs(w) for w in inverse(GEOMETRY, final)) == pytest.approx(10.0)
    assert final.vy / final.vx == pytest.approx(1.0)
    assert final.wz / final.vx == pytest.approx(2.0 / 0.6)


def test_feed_forward_alone_gives_set_point_over_top_speed() -> None:
    motion = controller(kp=0.0, ki=0.0, kd=0.0)
    for i in range(100):
        motion.step(i * 0.02, Twist(0.3, 0.0, 0.0), i * 0.02, AT_REST)
    wheel = 0.3 / GEOMETRY.wheel_radius_m
    assert motion.last.duties == pytest.approx((wheel / 20.0,) * 4)


def test_pid_tracks_the_set_points_despite_drag() -> None:
    motion = controller(kp=0.05, ki=0.5)
    plant = Plant(top_speed=20.0, drag=2.0)
    measured, period = AT_REST, motion.period_s
    command = Twist(0.2, 0.1, 0.3)
    for i in range(300):
        now = i * period
        duties = motion.step(now, command, now, measured)
        measured = plant.advance(duties, period)
    tracked = forward(GEOMETRY, measured)
    assert (tracked.vx, tracked.vy, tracked.wz) == pytest.approx((0.2, 0.1, 0.3), abs=0.01)


def test_anti_windup_bounds_the_integral_while_the_wheel_is_stalled() -> None:
    motion = controller(kp=0.0, ki=1.0, integral_limit=0.3)
    for i in range(200):  # wheels blocked: the error never goes away (for 4 s, within the stall timeout)
        motion.step(i * 0.02, Twist(0.3, 0.0, 0.0), i * 0.02, AT_REST)
    feed_forward = 0.3 / GEOMETRY.wheel_radius_m / 20.0
    assert motion.last.duties == pytest.approx((feed_forward + 0.3,) * 4)
    # Released, the wheel overshoots only by the bounded integral, which unwinds.
    duties = motion.step(4.0, Twist(0.3, 0.0, 0.0), 4.0, motion.last.wheel_setpoints)
    assert duties == pytest.approx((feed_forward + 0.3,) * 4)


def test_duties_never_exceed_the_duty_limit() -> None:
    motion = MotionController(GEOMETRY, ControlConfig(kp=5.0, stall_timeout_s=5.0), TeleopConfig(), duty_limit=0.7)
    for i in range(100):
        duties = motion.step(i * 0.02, Twist(0.6, 0.0, 0.0), i * 0.02, (-50.0, -50.0, -50.0, -50.0))
        assert all(abs(d) <= 0.7 for d in duties)
    assert motion.last.duties == (0.7, 0.7, 0.7, 0.7)


def test_stop_command_ramps_down_then_idles_with_motors_off() -> None:
    motion = controller()
    period = motion.period_s
    for i in range(50):
        motion.step(i * period, Twist(0.4, 0.0, 0.0), i * period, AT_REST)
    speeds = []
    for i in range(50, 100):
        motion.step(i * period, Twist(0.0, 0.0, 0.0), i * period, AT_REST)
        speeds.append(motion.last.setpoint.vx)
    assert speeds[0] == pytest.approx(0.4 - motion.teleop.max_linear_accel_mps2 * period)
    assert motion.last.state is ControlState.IDLE
    assert motion.last.duties == (0.0, 0.0, 0.0, 0.0)


def test_a_late_step_brakes_by_the_time_that_passed_but_speeds_up_by_a_few_periods_at_most() -> None:
    # A loop starved by a busy machine: the motors held their duty through the gap, so a stop must not be stretched
    # by it (braking follows the wall clock), while a start must not jump to speed (speeding is bounded).
    motion = controller()
    period, accel = motion.period_s, motion.teleop.max_linear_accel_mps2
    now = 0.0
    for _ in range(50):
        motion.step(now, Twist(0.4, 0.0, 0.0), now, AT_REST)
        now += period
    assert motion.last.setpoint.vx == pytest.approx(0.4)
    # the stop arrives on time; the step after it comes 0.3 s late (16 periods since the last step, beyond the bound)
    last_step, late = now - period, 0.3
    motion.step(now + late, Twist(0.0, 0.0, 0.0), now, AT_REST)
    assert motion.last.setpoint.vx == pytest.approx(0.4 - accel * (now + late - last_step))
    motion.step(now + late + 0.1, Twist(0.0, 0.0, 0.0), now, AT_REST)
    assert motion.last.state is ControlState.IDLE, "the stop finishes on the wall clock's ramp"
    assert motion.last.duties == (0.0, 0.0, 0.0, 0.0)
    start_at = now + 1.0  # a command after a pause: its step is 0.6 s after the one before
    motion.step(start_at, Twist(0.4, 0.0, 0.0), start_at, AT_REST)
    assert motion.last.setpoint.vx == pytest.approx(accel * 5 * period), "a late step sped up by all the time passed"


def test_a_reversal_on_time_passes_through_zero_within_one_step() -> None:
    motion = controller()
    period, accel = motion.period_s, motion.teleop.max_linear_accel_mps2
    motion.step(0.0, Twist(0.01, 0.0, 0.0), 0.0, AT_REST)  # half a step's worth of speed: the reversal crosses zero
    before = motion.last.setpoint.vx
    assert before == pytest.approx(0.01)
    motion.step(period, Twist(-0.4, 0.0, 0.0), period, AT_REST)
    assert motion.last.setpoint.vx == pytest.approx(before - accel * period)


def test_a_broken_encoder_reading_falls_back_to_feed_forward() -> None:
    motion = controller()
    for i in range(100):
        duties = motion.step(i * 0.02, Twist(0.3, 0.0, 0.0), i * 0.02, (math.nan, 0.0, math.inf, 0.0))
        assert all(math.isfinite(d) for d in duties)
    assert motion.last.duties[0] == pytest.approx(0.3 / GEOMETRY.wheel_radius_m / 20.0)
