"""The mecanum robot's true motion from its motor duties: DC motors, wheels, slip and the body.

Theory of operation: each motor is a first-order system, `tau dw/dt = w_ss(duty) - w`, whose steady speed is zero
inside the deadband (static friction) and rises linearly to the motor's top speed at full duty (saturation: duty is
clipped to [-1, 1]). Duty is constant between two steps, so the motor's speed and the wheel's angle are advanced
in closed form: the step length never affects them, only when the duty changes. The wheels' angle increments are
their true turns, which the encoders count. The ground moves each wheel by only its traction times its rim
travel (see `robotd.sim.floor`); the body's displacement is the paper's eq. 1 applied to those effective turns,
with the sideways component scaled by the rollers' lateral efficiency, rotated into the world at the step's
mid-heading.

Not modelled: motor current limits, battery sag, load torque, wheel inertia coupling through the body, rollers'
discrete contact; traction is evaluated at the step's start pose (steps are millimetres long).
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass

from robotd.kinematics import Geometry, forward
from robotd.sim.floor import Floor

Quad = tuple[float, float, float, float]

_AT_REST_RAD_S = 1e-6  # a coasting motor slower than this has stopped (a micro-radian per second)


@dataclass(frozen=True, slots=True)
class MotorParams:
    """The four DC motors with their gearboxes, as seen at the wheel."""

    max_speed_rad_s: float = 22.0
    time_constant_s: float = 0.08
    deadband: float = 0.06
    gain_spread: float = 0.03


@dataclass(frozen=True, slots=True)
class Pose:
    """The robot centre's true pose in the world: x, y in m, theta in rad (unwrapped)."""

    x: float
    y: float
    theta: float


class Motors:
    """Four first-order DC motors: duty in, wheel speed and angle out (closed-form steps)."""

    def __init__(self, params: MotorParams, seed: int) -> None:
        rng = random.Random(f"robotd-sim:{seed}:motors")
        self.params = params
        self.gains = tuple(max(0.1, 1.0 + rng.gauss(0.0, params.gain_spread)) for _ in range(4))
        self.speeds: list[float] = [0.0, 0.0, 0.0, 0.0]

    def steady_speed(self, wheel: int, duty: float) -> float:
        """The speed (rad/s) motor `wheel` settles at under a constant duty."""
        magnitude = min(1.0, abs(duty))
        deadband = self.params.deadband
        if magnitude <= deadband:
            return 0.0
        speed = self.gains[wheel] * self.params.max_speed_rad_s * (magnitude - deadband) / (1.0 - deadband)
        return speed if duty > 0 else -speed

    def advance(self, duties: Quad, dt: float) -> Quad:
        """Advance every motor by dt under constant duties; returns each wheel's angle increment (rad)."""
        tau = self.params.time_constant_s
        decay = math.exp(-dt / tau)
        increments = []
        for wheel in range(4):
            target = self.steady_speed(wheel, duties[wheel])
            start = self.speeds[wheel]
            speed = target + (start - target) * decay
            if target == 0.0 and abs(speed) < _AT_REST_RAD_S:  # static friction holds a coasting motor still
                speed = 0.0
            self.speeds[wheel] = speed
            increments.append(target * dt + (start - target) * tau * (1.0 - decay) if start or target else 0.0)
        return (increments[0], increments[1], increments[2], increments[3])


class Body:
    """The robot's body on the floor: wheel turns in, true pose out."""

    def __init__(self, geometry: Geometry, floor: Floor, pose: Pose) -> None:
        self.geometry = geometry
        self.floor = floor
        self.x, self.y, self.theta = pose.x, pose.y, pose.theta
        lx, ly = geometry.lx_m, geometry.ly_m
        self._wheel_positions = ((lx, ly), (lx, -ly), (-lx, ly), (-lx, -ly))  # FL FR RL RR in the body frame

    @property
    def pose(self) -> Pose:
        """The current true pose."""
        return Pose(self.x, self.y, self.theta)

    def wheel_points(self) -> list[tuple[float, float]]:
        """Where each wheel touches the floor, in the world frame."""
        c, s = math.cos(self.theta), math.sin(self.theta)
        return [(self.x + c * bx - s * by, self.y + s * bx + c * by) for bx, by in self._wheel_positions]

    def tractions(self) -> Quad:
        """Each wheel's traction at the current pose."""
        return self.floor.tractions(self.wheel_points())

    def move(self, wheel_turns: Quad) -> None:
        """Move the body by the wheels' true turns (rad) over one step, after slip (paper eq. 1 on ground travel)."""
        if not any(wheel_turns):  # at rest: nothing to move (saves the floor's waves in every pause)
            return
        t1, t2, t3, t4 = self.tractions()
        a1, a2, a3, a4 = wheel_turns[0] * t1, wheel_turns[1] * t2, wheel_turns[2] * t3, wheel_turns[3] * t4
        ground = forward(self.geometry, (a1, a2, a3, a4))  # ground travel of the wheels: the body's displacement
        dx, dy, dtheta = ground.vx, ground.vy * self.floor.params.lateral_efficiency, ground.wz
        mid = self.theta + 0.5 * dtheta
        c, s = math.cos(mid), math.sin(mid)
        self.x += c * dx - s * dy
        self.y += s * dx + c * dy
        self.theta += dtheta

    def beacon_position(self, offset: tuple[float, float]) -> tuple[float, float]:
        """World position of a point mounted at `offset` in the body frame (the beacon's lever arm)."""
        c, s = math.cos(self.theta), math.sin(self.theta)
        return (self.x + c * offset[0] - s * offset[1], self.y + s * offset[0] + c * offset[1])


class Robot:
    """Motors, wheels and body together: `step(duties, dt)` advances the true state."""

    def __init__(self, geometry: Geometry, motors: Motors, floor: Floor, pose: Pose) -> None:
        self.motors = motors
        self.body = Body(geometry, floor, pose)
        self.wheel_angles: list[float] = [0.0, 0.0, 0.0, 0.0]

    def step(self, duties: Quad, dt: float) -> None:
        """Advance the robot by dt seconds with the duties held constant (duty > 0 turns a wheel forward)."""
        if dt <= 0.0:
            return
        turns = self.motors.advance(duties, dt)
        for wheel in range(4):
            self.wheel_angles[wheel] += turns[wheel]
        self.body.move(turns)

    def encoder_counts(self, counts_per_rev: int) -> tuple[int, int, int, int]:
        """Cumulative decoded counts of each wheel's encoder (forward positive), from its true angle."""
        scale = counts_per_rev / (2.0 * math.pi)
        a = self.wheel_angles
        return (
            math.floor(a[0] * scale),
            math.floor(a[1] * scale),
            math.floor(a[2] * scale),
            math.floor(a[3] * scale),
        )
