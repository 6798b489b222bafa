"""The doctor's spin test, wheels off the ground: each wheel driven forward in turn while all four encoders count.

For each wheel the four counts are read, the wheel is driven at `duty` through a ramp and a measuring window, stopped
and left to coast, and the counts are read at the window's edges and at the end. The four runs tell: did the driven
wheel's encoder, and only it, count (cross-wiring otherwise); which way; and at a speed that fits the configured
counts per turn (the speed this duty should give by control.wheel_max_speed_rad_s, within a factor of two).

An encoder cannot tell a reversed motor from a reversed encoder, nor see both reversed: a person watching the wheel
can. With a person watching, the doctor asks after each wheel which way it turned; unwatched, a backward count names
both possible causes.
"""

from __future__ import annotations

import asyncio
import enum
import math
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

from robotd.config.model import WHEELS, EncoderPins, MotorPins, RobotdConfig
from robotd.tools.checklist import Finding, failed, passed
from robotd.tools.gpio_backend import Counts, WheelDrive

MOVED_TURNS = 1 / 36
"""An encoder that counted less than this part of a turn (10 degrees) did not move."""
SPEED_FACTOR = 2.0
"""The speed by the configured counts per turn may differ from the expected one by this factor (load, deadband):
a wrong decoding (x1 for x4) or an encoder on the motor shaft (times the gear ratio) is off by more."""


class Seen(enum.Enum):
    """What the person watching saw the driven wheel do."""

    FORWARD = "f"
    BACKWARD = "b"
    STILL = "n"
    UNSEEN = ""


@dataclass(frozen=True, slots=True)
class SpinPlan:
    """How hard and how long each wheel is driven."""

    duty: float = 0.5
    ramp_s: float = 0.4  # to full speed before measuring (a motor's time constant is about 0.1 s)
    measure_s: float = 0.8
    coast_s: float = 0.6  # to a stop before the next wheel


@dataclass(frozen=True, slots=True)
class WheelRun:
    """What the encoders did while one wheel was driven."""

    wheel: int
    moved: Counts  # each encoder's count change, from before the drive to after the coast
    rates: tuple[float, float, float, float]  # each encoder's counts per second in the measuring window
    seen: Seen


Ask = Callable[[str], Awaitable[Seen]]


async def spin_wheels(
    drive: WheelDrive,
    counts: Callable[[], Counts],
    plan: SpinPlan,
    *,
    ask: Ask | None = None,
    sleep: Callable[[float], Awaitable[None]] = asyncio.sleep,
    clock: Callable[[], float] = time.monotonic,
) -> list[WheelRun]:
    """Drive each wheel in turn and read the encoders; every motor is off whenever this returns or raises."""
    runs = []
    for wheel, name in enumerate(WHEELS):
        before = counts()
        try:
            await asyncio.to_thread(drive.drive, wheel, plan.duty)
            await sleep(plan.ramp_s)
            start, start_t = counts(), clock()
            await sleep(plan.measure_s)
            end, end_t = counts(), clock()
        finally:
            await asyncio.to_thread(drive.stop)
        await sleep(plan.coast_s)
        after = counts()
        seen = await ask(name) if ask is not None else Seen.UNSEEN
        span = max(end_t - start_t, 1e-9)
        moved = (after[0] - before[0], after[1] - before[1], after[2] - before[2], after[3] - before[3])
        rates = tuple((end[j] - start[j]) / span for j in range(4))
        runs.append(WheelRun(wheel, moved, (rates[0], rates[1], rates[2], rates[3]), seen))
    return runs


def diagnose(runs: list[WheelRun], config: RobotdConfig, plan: SpinPlan) -> list[Finding]:
    """One finding per wheel: moves, right way, plausible counts per turn, only its own encoder counting."""
    threshold = config.encoders.counts_per_rev * MOVED_TURNS
    movers = {run.wheel: [j for j in range(4) if abs(run.moved[j]) >= threshold] for run in runs}
    return [_wheel_finding(run, movers, config, plan) for run in runs]


def _pins(config: RobotdConfig, wheel: str) -> tuple[EncoderPins, MotorPins]:
    return getattr(config.encoders.wheels, wheel), getattr(config.motors.wheels, wheel)


def _wheel_finding(run: WheelRun, movers: dict[int, list[int]], config: RobotdConfig, plan: SpinPlan) -> Finding:
    name = WHEELS[run.wheel]
    check = f"spin {name}"
    encoder, motor = _pins(config, name)
    moved = movers[run.wheel]
    if not moved:
        if run.seen in (Seen.FORWARD, Seen.BACKWARD):
            return failed(
                check,
                f"{name} turned but no encoder counted",
                f"check {name}'s encoder: A on GPIO {encoder.a}, B on GPIO {encoder.b}, its supply and ground",
            )
        return failed(
            check,
            f"{name} did not move: no encoder counted while its motor was driven at duty {plan.duty:g}",
            f"check {name}'s motor: enable GPIO {motor.enable}, IN1 GPIO {motor.in1}, IN2 GPIO {motor.in2}, the"
            " L298's motor supply, the wheel free to turn; or a larger --spin-duty",
        )
    if len(moved) > 1:
        names = ", ".join(WHEELS[j] for j in moved)
        return failed(
            check,
            f"driving {name} moved the encoders of {names}",
            "two channels share a wire: check the L298 outputs and the encoder lines of these wheels",
        )
    reader = moved[0]
    if reader != run.wheel:
        return _crossed(check, run, reader, movers, config)
    return _direction_and_speed(check, run, config, plan)


def _crossed(check: str, run: WheelRun, reader: int, movers: dict[int, list[int]], config: RobotdConfig) -> Finding:
    name, other = WHEELS[run.wheel], WHEELS[reader]
    if run.seen is Seen.STILL:
        return failed(
            check,
            f"{name}'s motor pins drive {other}'s wheel ({name} stood still, {other}'s encoder counted)",
            f"swap the motor cables of {name} and {other} at the L298, or their pins in motors.wheels",
        )
    swapped = movers.get(reader) == [run.wheel]
    detail = f"{other} encoder reads {name}'s wheel"
    if run.seen is Seen.UNSEEN:
        detail += f" (or {name}'s motor pins drive {other}'s wheel: watch which wheel turns)"
    encoder, _ = _pins(config, other)
    if swapped:
        fix = f"swap the encoder cables of {name} and {other}, or swap encoders.wheels.{name} and .{other}"
    else:
        fix = f"connect {name}'s encoder, not {other}'s, to GPIO {encoder.a} and {encoder.b}, or fix encoders.wheels"
    return failed(check, detail, fix)


def _direction_and_speed(check: str, run: WheelRun, config: RobotdConfig, plan: SpinPlan) -> Finding:
    name = WHEELS[run.wheel]
    encoder, motor = _pins(config, name)
    counted_forward = run.moved[run.wheel] > 0
    motor_fix = f"swap IN1/IN2 (GPIO {motor.in1}, {motor.in2}) or set motors.wheels.{name}.sign: {-motor.sign}"
    encoder_fix = (
        f"swap its A/B wires (GPIO {encoder.a}, {encoder.b}) or set encoders.wheels.{name}.sign: {-encoder.sign}"
    )
    if counted_forward and run.seen is Seen.BACKWARD:
        return failed(
            check, f"{name} motor and encoder both reversed (it turned backward, counting forward)",
            f"{motor_fix}; and {encoder_fix}",
        )  # fmt: skip
    if not counted_forward and run.seen is Seen.FORWARD:
        return failed(check, f"{name} encoder reversed: it counts backward while the wheel turns forward", encoder_fix)
    if not counted_forward and run.seen is Seen.BACKWARD:
        return failed(check, f"{name} motor reversed: the wheel turns backward when driven forward", motor_fix)
    if not counted_forward:
        return failed(
            check, f"{name} counts backward when driven forward: its motor or its encoder is reversed",
            f"watch the wheel (run robotd doctor --spin in a terminal and answer) to tell which; motor: {motor_fix};"
            f" encoder: {encoder_fix}",
        )  # fmt: skip
    if run.seen is Seen.STILL:
        return failed(
            check,
            f"{name}'s encoder counted, yet {name} stood still: its motor drives another wheel whose encoder is on"
            f" {name}'s pins",
            "check which wheel turns for each motor channel, and the encoder cables",
        )
    cpr = config.encoders.counts_per_rev
    speed = abs(run.rates[run.wheel]) * 2 * math.pi / cpr
    duty = min(abs(plan.duty), config.motors.duty_limit)
    expected = duty * config.control.wheel_max_speed_rad_s
    by_config = f"{speed:.1f} rad/s by {cpr} counts a turn, {expected:.1f} expected at duty {duty:g}"
    if not expected / SPEED_FACTOR <= speed <= expected * SPEED_FACTOR:
        return failed(
            check,
            f"{name} counts per turn implausible: {by_config} (control.wheel_max_speed_rad_s x duty)",
            f"check encoders.ppr ({config.encoders.ppr}: pulses a wheel turn, times the gear ratio when the encoder"
            f" is on the motor shaft) and encoders.decoding ({config.encoders.decoding}); or measure"
            " control.wheel_max_speed_rad_s",
        )
    watched = "as you saw" if run.seen is Seen.FORWARD else "by its encoder (nobody watched)"
    return passed(check, f"forward {watched}, {by_config}; no other encoder counted")
