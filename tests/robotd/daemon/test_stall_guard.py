"""The stall guard of the motion controller, on a hand-driven clock: a wheel that is driven but does not turn (a dead
encoder, a reversed one, a blocked wheel) stops the robot and holds a fault until a fresh command."""

from __future__ import annotations

import math

import pytest

from robotd.config.model import ConfigError, ControlConfig, TeleopConfig, parse
from robotd.daemon.control import ControlState, MotionController, StallFault, Wheels
from robotd.kinematics import Geometry, Twist, inverse

GEOMETRY = Geometry()
SLOW = Twist(0.1, 0.0, 0.0)  # the case: a held 0.1 m/s command
STOP = Twist(0.0, 0.0, 0.0)


class Wheel:
    """A first-order motor with a deadband: speed follows (duty beyond the deadband) * top speed."""

    def __init__(self, top_speed: float = 22.0, deadband: float = 0.06, tau: float = 0.05) -> None:
        self.speed = 0.0
        self.top_speed, self.deadband, self.tau = top_speed, deadband, tau

    def advance(self, duty: float, dt: float) -> float:
        magnitude = max(0.0, abs(duty) - self.deadband) / (1.0 - self.deadband)
        target = math.copysign(magnitude * self.top_speed, duty)
        self.speed += (target - self.speed) * min(1.0, dt / self.tau)
        return self.speed


class Robot:
    """Four wheels under a controller; `encoders` maps the true wheel speeds to what the controller reads."""

    def __init__(self, motion: MotionController, encoders: list[float] | None = None) -> None:
        self.motion = motion
        self.wheels = [Wheel() for _ in range(4)]
        self.encoders = encoders if encoders is not None else [1.0, 1.0, 1.0, 1.0]  # per-wheel gain: 0 = dead
        self.now = 0.0
        self.faults: list[StallFault | None] = []
        self.peak_duties = [0.0, 0.0, 0.0, 0.0]
        motion.on_fault = self.faults.append

    def measured(self) -> Wheels:
        a, b, c, d = (gain * wheel.speed for gain, wheel in zip(self.encoders, self.wheels, strict=True))
        return (a, b, c, d)

    def run(self, command: Twist | None, seconds: float, *, fresh: bool = True) -> None:
        """Step for `seconds` with `command` arriving every period (`fresh`), or sent once at the start (not fresh)."""
        period = self.motion.period_s
        sent_at = self.now
        for _ in range(round(seconds / period)):
            if fresh:
                sent_at = self.now
            duties = self.motion.step(self.now, command, sent_at if command is not None else None, self.measured())
            for i, (wheel, duty) in enumerate(zip(self.wheels, duties, strict=True)):
                wheel.advance(duty, period)
                self.peak_duties[i] = max(self.peak_duties[i], abs(duty))
            self.now += period


def motion(**control: float) -> MotionController:
    return MotionController(GEOMETRY, ControlConfig(**control), TeleopConfig())


def test_a_dead_encoder_under_a_held_command_stops_every_motor_instead_of_winding_up() -> None:
    robot = Robot(motion(), encoders=[0.0, 1.0, 1.0, 1.0])  # the front-left encoder gives no edges
    robot.run(SLOW, 10.0)
    c = robot.motion.control
    assert robot.motion.last.state is ControlState.FAULT
    assert robot.motion.last.duties == (0.0, 0.0, 0.0, 0.0)
    assert robot.motion.fault is not None
    assert robot.motion.fault.wheels == ("front_left",)
    assert robot.faults == [robot.motion.fault], "the fault is reported once, when it latches"
    # Without the guard the wheel winds up to feed-forward + integral_limit (0.65 here) and stays there. With it, the
    # duty never gets past the margin plus what the PID adds during the stall time.
    setpoint = abs(inverse(GEOMETRY, SLOW)[0])
    feed_forward = setpoint / c.wheel_max_speed_rad_s
    pushing_s = c.stall_timeout_s + 2 * robot.motion.period_s
    bound = feed_forward + c.stall_duty_margin + (c.kp + c.ki * pushing_s) * setpoint
    assert robot.peak_duties[0] < bound < feed_forward + c.integral_limit


def test_the_fault_latches_after_stall_timeout_s_of_pushing_not_before() -> None:
    robot = Robot(motion(stall_timeout_s=2.0), encoders=[0.0, 1.0, 1.0, 1.0])
    pushing_since = None
    while robot.motion.fault is None and robot.now < 20.0:
        robot.run(SLOW, robot.motion.period_s)
        c = robot.motion.control
        duty = robot.motion.last.duties[0]
        setpoint = robot.motion.last.wheel_setpoints[0]
        if pushing_since is None and duty - setpoint / c.wheel_max_speed_rad_s > c.stall_duty_margin:
            pushing_since = robot.now - robot.motion.period_s
    assert pushing_since is not None
    assert robot.motion.fault is not None
    assert robot.motion.fault.since - pushing_since == pytest.approx(2.0, abs=1.5 * robot.motion.period_s)


def test_repeats_of_the_held_command_keep_the_fault_and_the_motors_off() -> None:
    robot = Robot(motion(), encoders=[0.0, 1.0, 1.0, 1.0])
    robot.run(SLOW, 3.0)
    assert robot.motion.fault is not None
    robot.run(SLOW, 5.0)  # the client keeps sending the same command, fresh datagrams all along
    assert robot.motion.last.state is ControlState.FAULT
    assert robot.motion.last.duties == (0.0, 0.0, 0.0, 0.0)
    assert len(robot.faults) == 1


@pytest.mark.parametrize("let_go", ["stop", "silence"])
def test_after_letting_go_a_fresh_command_clears_the_fault_and_drives_again(let_go: str) -> None:
    robot = Robot(motion(), encoders=[0.0, 1.0, 1.0, 1.0])
    robot.run(SLOW, 3.0)
    fault = robot.motion.fault
    assert fault is not None
    if let_go == "stop":
        robot.run(STOP, 0.2)
    else:
        robot.run(None, 0.2)
    assert robot.motion.fault == fault, "the fault holds while the operator has let go"
    assert robot.motion.last.duties == (0.0, 0.0, 0.0, 0.0)
    robot.run(SLOW, robot.motion.period_s)
    assert robot.faults == [fault, None]
    assert robot.motion.last.state is ControlState.DRIVING
    assert any(robot.motion.last.duties)
    robot.run(SLOW, 5.0)  # the encoder is still dead: the guard catches it again
    assert len(robot.faults) == 3
    again = robot.faults[-1]
    assert again is not None
    assert again.since > fault.since


def test_a_reversed_encoder_is_caught_too() -> None:
    robot = Robot(motion(), encoders=[1.0, -1.0, 1.0, 1.0])  # front-right counts backwards: positive feedback
    robot.run(SLOW, 5.0)
    assert robot.motion.fault is not None
    assert robot.motion.fault.wheels == ("front_right",)


def test_all_four_encoders_dead_name_all_four_wheels() -> None:
    robot = Robot(motion(), encoders=[0.0, 0.0, 0.0, 0.0])  # the encoder cable is out
    robot.run(Twist(0.0, 0.2, 0.0), 5.0)
    assert robot.motion.fault is not None
    assert set(robot.motion.fault.wheels) == {"front_left", "front_right", "rear_left", "rear_right"}


def test_healthy_wheels_never_fault_driving_the_paper_square_with_reversals_and_creeping() -> None:
    robot = Robot(motion())
    for twist in (Twist(0.3, 0.0, 0.0), Twist(0.0, -0.3, 0.0), Twist(-0.3, 0.0, 0.0), Twist(0.0, 0.3, 0.0)) * 2:
        robot.run(twist, 3.0)
    robot.run(Twist(0.0, 0.0, 1.5), 2.0)
    robot.run(Twist(0.005, 0.0, 0.0), 10.0)  # below the motors' deadband at first: the PID must wind up to move
    robot.run(Twist(-0.6, 0.6, 2.0), 3.0)
    assert robot.faults == []
    assert robot.motion.last.state is ControlState.DRIVING


def test_a_wheel_blocked_for_less_than_the_stall_timeout_does_not_fault() -> None:
    robot = Robot(motion(stall_timeout_s=1.0))
    robot.run(SLOW, 1.0)
    for _ in range(5):  # blocked for 0.6 s at a time, then free again
        robot.encoders[2] = 0.0
        robot.run(SLOW, 0.6)
        robot.encoders[2] = 1.0
        robot.run(SLOW, 1.0)
    assert robot.faults == []


def test_a_non_finite_reading_is_driven_open_loop_and_is_not_a_stall() -> None:
    robot = Robot(motion(), encoders=[math.nan, 1.0, 1.0, 1.0])
    robot.run(SLOW, 5.0)
    assert robot.faults == []


def test_a_stall_margin_the_integral_cannot_reach_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match=r"control: stall_duty_margin .* must be below integral_limit"):
        parse("control: {integral_limit: 0.2, stall_duty_margin: 0.3}")
    with pytest.raises(ConfigError, match=r"control\.stall_timeout_s: .*5\.0"):
        parse("control: {stall_timeout_s: 100.0}")
    assert ControlConfig(ki=0.0, integral_limit=0.1, stall_duty_margin=0.3).stall_duty_margin == 0.3
