"""The motion control loop: teleop twist in, motor duties out. Pure code: no I/O, no clock, no asyncio.

Theory of operation, once per control period (`step`):
1. Deadman: without a command received within `deadman_timeout_s`, the controller is in DEADMAN: the duties are
   exactly 0.0, the set-points are reset to rest and every integrator is cleared, so that driving resumes with a
   ramp from standstill rather than a jump back to the old speed.
2. Limits: the command is clamped per axis to the teleop speed limits, then scaled down as a whole (keeping its
   direction) until no wheel needs more than `wheel_max_speed_rad_s`.
3. Slew: each axis of the set-point twist moves towards the target by at most its acceleration limit times dt. A
   late step (a loop starved by a busy machine) speeds up by at most a few periods' worth, but brakes by the whole
   time that has passed: the ramp down is where the operator expects it on the wall clock, so a stop is never
   stretched by the machine's load (the motors held their duty meanwhile).
4. Inverse kinematics (the exact inverse of the paper's eq. 1) turns the set-point twist into wheel speed set-points.
5. Per wheel: duty = feed-forward (set-point / wheel_max_speed_rad_s) + PID on the measured wheel speed. The
   integral is bounded by `integral_limit` and frozen while the duty saturates in the direction of the error
   (anti-windup by clamping); the derivative acts on the measurement so that set-point steps do not kick it.
6. At rest (target and set-points zero) the controller is IDLE: duties exactly 0.0, so the motors do not hum
   trying to hold zero speed against encoder noise.
7. Stall guard: a wheel the PID drives more than `stall_duty_margin` beyond its feed-forward, in the direction of its
   set-point, while it turns at less than a tenth of that set-point in that direction, for `stall_timeout_s`, has
   stalled (a dead or unplugged encoder, a wrong encoder sign, a blocked wheel): left alone the integral would wind
   the duty up to feed-forward + integral_limit and run the real wheel away. The controller latches a `StallFault`
   and is in FAULT: every duty is 0.0, because a mecanum base cannot hold its course on three wheels. The fault holds
   until a fresh command: the operator lets go (a stop, a command to rest, or silence past the deadman), then
   commands motion again. A client repeats a held command many times a second, so a mere repeat is not fresh: it
   would re-arm the wheel at once and repeat the runaway every stall time.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable
from dataclasses import dataclass, field

from robotd.config.model import WHEELS, ControlConfig, TeleopConfig
from robotd.kinematics import Geometry, Twist, inverse

Wheels = tuple[float, float, float, float]
ZERO_WHEELS: Wheels = (0.0, 0.0, 0.0, 0.0)
REST = Twist(0.0, 0.0, 0.0)

# A control period longer than this many nominal periods (a stalled loop) is integrated as this many: the PID must
# not take one giant step from a stale measurement, nor the set-point one giant step up to speed (braking is not
# bounded: see the module docstring, step 3).
_MAX_PERIODS_PER_STEP = 5.0
# A stalled wheel turns at less than this fraction of its set-point in the commanded direction: a dead encoder reads 0,
# a reversed one reads the wrong way, a blocked wheel barely creeps; a loaded but turning wheel stays well above it.
_STALL_PROGRESS_FRACTION = 0.1


class ControlState(enum.Enum):
    """What the controller is doing with the motors."""

    DEADMAN = "deadman"  # no valid command within deadman_timeout_s: motors off
    IDLE = "idle"  # commanded to rest and at rest: motors off
    DRIVING = "driving"  # tracking wheel speed set-points
    FAULT = "fault"  # a wheel stalled: motors off until a fresh command (see StallFault)


@dataclass(frozen=True, slots=True)
class StallFault:
    """Wheels that were driven hard but did not turn, and the monotonic time the controller stopped the motors."""

    wheels: tuple[str, ...]  # names from robotd.config.model.WHEELS
    since: float


@dataclass(slots=True)
class _WheelPid:
    """PID state of one wheel."""

    integral: float = 0.0  # accumulated error, rad
    last_measured: float | None = None
    stalled_since: float | None = None  # when the stall condition started to hold without a break


@dataclass(frozen=True, slots=True)
class ControlOutput:
    """Everything one control step decided (for diagnostics and the simulator)."""

    duties: Wheels
    wheel_setpoints: Wheels  # rad/s
    setpoint: Twist  # slew-limited body twist
    state: ControlState


@dataclass(slots=True)
class MotionController:
    """Teleop twist to motor duties: limits, slew, deadman, inverse kinematics and per-wheel PID."""

    geometry: Geometry
    control: ControlConfig
    teleop: TeleopConfig
    duty_limit: float = 1.0
    on_fault: Callable[[StallFault | None], None] | None = None
    """Called with the fault when one latches and with None when it clears (the daemon logs it)."""
    _setpoint: Twist = field(default=REST, init=False)
    _wheels: list[_WheelPid] = field(default_factory=lambda: [_WheelPid() for _ in range(4)], init=False)
    _last_step: float | None = field(default=None, init=False)
    _last: ControlOutput = field(
        default_factory=lambda: ControlOutput(ZERO_WHEELS, ZERO_WHEELS, REST, ControlState.DEADMAN), init=False
    )
    _fault: StallFault | None = field(default=None, init=False)
    _let_go: bool = field(default=False, init=False)  # the operator released the command since the fault latched

    def __post_init__(self) -> None:
        if not 0.0 < self.duty_limit <= 1.0:
            raise ValueError(f"duty_limit must be in (0, 1], got {self.duty_limit}")

    @property
    def period_s(self) -> float:
        """Nominal control period."""
        return 1.0 / self.control.rate_hz

    @property
    def last(self) -> ControlOutput:
        """The output of the latest step (motors off before the first)."""
        return self._last

    @property
    def fault(self) -> StallFault | None:
        """The stall fault holding the motors off, if any."""
        return self._fault

    def reset(self) -> None:
        """Forget the set-points and integrators: the next step starts from rest."""
        self._setpoint = REST
        for wheel in self._wheels:
            wheel.integral = 0.0
            wheel.last_measured = None
            wheel.stalled_since = None

    def step(
        self, now: float, command: Twist | None, command_time: float | None, measured_wheel_speeds: Wheels
    ) -> Wheels:
        """One control period: the duties (FL, FR, RL, RR, each in [-duty_limit, duty_limit]) for the motors.

        `command` is the latest valid teleop twist and `command_time` the monotonic time it arrived; None for
        either means no command. `measured_wheel_speeds` are the encoders' wheel speeds in rad/s.
        """
        return self.step_output(now, command, command_time, measured_wheel_speeds).duties

    def step_output(
        self, now: float, command: Twist | None, command_time: float | None, measured_wheel_speeds: Wheels
    ) -> ControlOutput:
        """`step`, returning the set-points and state as well as the duties."""
        elapsed = self._elapsed(now)
        dt = min(elapsed, _MAX_PERIODS_PER_STEP * self.period_s)
        if command is None or command_time is None or not _finite_twist(command):
            return self._released(ControlState.DEADMAN)
        if now - command_time > self.teleop.deadman_timeout_s:
            return self._released(ControlState.DEADMAN)
        target = self._limited(command)
        if self._fault is not None:
            if target == REST:
                return self._released(ControlState.IDLE)
            if not self._let_go:  # the command that was held when the wheel stalled, repeated
                return self._motors_off(ControlState.FAULT)
            self._clear_fault()
        self._setpoint = self._slewed(self._setpoint, target, dt, elapsed)
        if self._setpoint == REST and target == REST:
            return self._motors_off(ControlState.IDLE)
        wheel_setpoints = inverse(self.geometry, self._setpoint)
        duties = tuple(
            self._pid(pid, setpoint, measured, dt)
            for pid, setpoint, measured in zip(self._wheels, wheel_setpoints, measured_wheel_speeds, strict=True)
        )
        stalled = self._stalled_wheels(now, _four(duties), wheel_setpoints, measured_wheel_speeds)
        if stalled:
            return self._latch_fault(now, stalled)
        self._last = ControlOutput(_four(duties), wheel_setpoints, self._setpoint, ControlState.DRIVING)
        return self._last

    def _elapsed(self, now: float) -> float:
        """Seconds since the previous step (never negative); the nominal period at the first."""
        previous, self._last_step = self._last_step, now
        if previous is None:
            return self.period_s
        return max(now - previous, 0.0)

    def _motors_off(self, state: ControlState) -> ControlOutput:
        self.reset()
        self._last = ControlOutput(ZERO_WHEELS, ZERO_WHEELS, REST, state)
        return self._last

    def _released(self, state: ControlState) -> ControlOutput:
        """Motors off because the operator let go (no command, or rest); a held fault stays until a fresh command."""
        if self._fault is not None:
            self._let_go = True
            return self._motors_off(ControlState.FAULT)
        return self._motors_off(state)

    def _stalled_wheels(self, now: float, duties: Wheels, setpoints: Wheels, measured: Wheels) -> tuple[str, ...]:
        """The wheels whose stall condition has held for `stall_timeout_s` (see the module docstring, step 7)."""
        c = self.control
        stalled: list[str] = []
        for name, pid, duty, setpoint, speed in zip(WHEELS, self._wheels, duties, setpoints, measured, strict=True):
            direction = math.copysign(1.0, setpoint)
            pushing = setpoint != 0.0 and (duty - setpoint / c.wheel_max_speed_rad_s) * direction > c.stall_duty_margin
            # a non-finite reading is not a stall: the PID then drives open-loop at the feed-forward, not pushing
            turning = speed * direction >= _STALL_PROGRESS_FRACTION * abs(setpoint)
            if not pushing or turning:
                pid.stalled_since = None
                continue
            if pid.stalled_since is None:
                pid.stalled_since = now
            if now - pid.stalled_since >= c.stall_timeout_s:
                stalled.append(name)
        return tuple(stalled)

    def _latch_fault(self, now: float, wheels: tuple[str, ...]) -> ControlOutput:
        self._fault, self._let_go = StallFault(wheels, now), False
        if self.on_fault is not None:
            self.on_fault(self._fault)
        return self._motors_off(ControlState.FAULT)

    def _clear_fault(self) -> None:
        self._fault, self._let_go = None, False
        if self.on_fault is not None:
            self.on_fault(None)

    def _limited(self, command: Twist) -> Twist:
        """The command clamped to the speed limits, then scaled so that no wheel exceeds its top speed."""
        t = self.teleop
        clamped = Twist(
            _clamp(command.vx, t.max_vx_mps), _clamp(command.vy, t.max_vy_mps), _clamp(command.wz, t.max_wz_rad_s)
        )
        fastest = max(abs(w) for w in inverse(self.geometry, clamped))
        if fastest <= self.control.wheel_max_speed_rad_s:
            return clamped
        scale = self.control.wheel_max_speed_rad_s / fastest  # keep the direction of travel, lose some speed
        return Twist(clamped.vx * scale, clamped.vy * scale, clamped.wz * scale)

    def _slewed(self, current: Twist, target: Twist, dt: float, elapsed: float) -> Twist:
        """`current` moved towards `target` by at most the acceleration limits: over dt (bounded) where an axis speeds
        up, over the whole elapsed time where it slows down."""
        linear, angular = self.teleop.max_linear_accel_mps2, self.teleop.max_angular_accel_rad_s2
        return Twist(
            _slewed_axis(current.vx, target.vx, linear * dt, linear * elapsed),
            _slewed_axis(current.vy, target.vy, linear * dt, linear * elapsed),
            _slewed_axis(current.wz, target.wz, angular * dt, angular * elapsed),
        )

    def _pid(self, pid: _WheelPid, setpoint: float, measured: float, dt: float) -> float:
        """Feed-forward plus PID for one wheel, with a bounded, clamped integral."""
        c = self.control
        feed_forward = setpoint / c.wheel_max_speed_rad_s
        if not math.isfinite(measured):  # a broken encoder reading: drive open-loop, do not integrate garbage
            pid.last_measured = None
            return _clamp(feed_forward, self.duty_limit)
        error = setpoint - measured
        derivative = 0.0
        if pid.last_measured is not None and dt > 0.0:
            derivative = -(measured - pid.last_measured) / dt
        pid.last_measured = measured
        candidate = pid.integral + error * dt
        if c.ki > 0.0:
            candidate = _clamp(candidate, c.integral_limit / c.ki)
        unsaturated = feed_forward + c.kp * error + c.ki * candidate + c.kd * derivative
        # Anti-windup: integrate only while the output is not saturated in the direction the error pushes it.
        if abs(unsaturated) < self.duty_limit or unsaturated * error < 0.0:
            pid.integral = candidate
        duty = feed_forward + c.kp * error + c.ki * pid.integral + c.kd * derivative
        return _clamp(duty, self.duty_limit)


def _clamp(value: float, limit: float) -> float:
    return max(-limit, min(limit, value))


def _towards(current: float, target: float, max_change: float) -> float:
    return current + _clamp(target - current, max_change)


def _slewed_axis(current: float, target: float, speeding: float, braking: float) -> float:
    """One axis towards target: by at most `braking` while its magnitude falls (towards zero, or a smaller speed the
    same way), by at most `speeding` while it rises. A reversal brakes to zero, then speeds up the other way by what
    is left of `speeding` (on time, braking == speeding: one limit through zero, as a plain slew)."""
    same_way = target * current > 0.0
    if current == 0.0 or (same_way and abs(target) >= abs(current)):
        return _towards(current, target, speeding)
    if same_way:
        return _towards(current, target, braking)
    if abs(current) > braking:  # stopping or reversing, not yet through zero
        return _towards(current, 0.0, braking)
    return _towards(0.0, target, max(speeding - abs(current), 0.0))


def _finite_twist(twist: Twist) -> bool:
    return math.isfinite(twist.vx) and math.isfinite(twist.vy) and math.isfinite(twist.wz)


def _four(values: tuple[float, ...]) -> Wheels:
    a, b, c, d = values
    return (a, b, c, d)
