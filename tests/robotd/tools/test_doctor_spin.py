"""The doctor's spin test on a fake robot with its wheels in the air: every wiring fault named, with its fix."""

from __future__ import annotations

import asyncio
import math

import pytest

from robotd.config.model import RobotdConfig, parse
from robotd.tools.checklist import Finding, Verdict
from robotd.tools.doctor_spin import Seen, SpinPlan, WheelRun, diagnose, spin_wheels

CONFIG = RobotdConfig()
PLAN = SpinPlan(duty=0.5, ramp_s=0.4, measure_s=0.8, coast_s=0.6)
# counts a second of a wheel at duty 0.5 as the configuration expects it: 0.5 x 20 rad/s, 6800 counts a turn
RATE = 0.5 * CONFIG.control.wheel_max_speed_rad_s / (2 * math.pi) * CONFIG.encoders.counts_per_rev


class FakeRobot:
    """Four wheels in the air on a fake clock; which wheel each motor turns, and which wheel each encoder reads."""

    def __init__(
        self,
        *,
        motor_of: tuple[int, ...] = (0, 1, 2, 3),
        motor_sign: tuple[int, ...] = (1, 1, 1, 1),
        encoder_of: tuple[int, ...] = (0, 1, 2, 3),
        encoder_sign: tuple[int, ...] = (1, 1, 1, 1),
        rate: tuple[float, ...] = (RATE, RATE, RATE, RATE),
    ) -> None:
        self.motor_of, self.motor_sign = motor_of, motor_sign
        self.encoder_of, self.encoder_sign = encoder_of, encoder_sign
        self.rate = rate
        self.now = 0.0
        self.turned = [0.0] * 4
        self.driven: tuple[int, float] | None = None
        self.calls: list[str] = []

    async def sleep(self, seconds: float) -> None:
        if self.driven is not None:
            motor, duty = self.driven
            wheel = self.motor_of[motor]
            self.turned[wheel] += self.motor_sign[motor] * math.copysign(self.rate[motor], duty) * seconds
        self.now += seconds

    def clock(self) -> float:
        return self.now

    def drive(self, wheel: int, duty: float) -> None:
        self.driven = (wheel, duty)
        self.calls.append(f"drive {wheel}")

    def stop(self) -> None:
        self.driven = None
        self.calls.append("stop")

    def close(self) -> None:
        self.stop()

    def counts(self) -> tuple[int, int, int, int]:
        c = [round(self.encoder_sign[k] * self.turned[self.encoder_of[k]]) for k in range(4)]
        return (c[0], c[1], c[2], c[3])


def spin(robot: FakeRobot, seen: str = "    ", config: RobotdConfig = CONFIG) -> list[Finding]:
    """Spin every wheel of the fake robot; `seen` is what the person answers for each wheel (' ' = not watched)."""
    answers = iter(Seen(s.strip()) for s in seen)

    async def ask(_wheel: str) -> Seen:
        return next(answers)

    runs = asyncio.run(spin_wheels(robot, robot.counts, PLAN, ask=ask, sleep=robot.sleep, clock=robot.clock))
    return diagnose(runs, config, PLAN)


def verdicts(findings: list[Finding]) -> list[Verdict]:
    return [f.verdict for f in findings]


def test_a_robot_wired_right_passes_every_wheel() -> None:
    findings = spin(FakeRobot())
    assert verdicts(findings) == [Verdict.PASS] * 4
    assert [f.check for f in findings] == ["spin front_left", "spin front_right", "spin rear_left", "spin rear_right"]
    assert "10.0 rad/s" in findings[0].detail
    assert "nobody watched" in findings[0].detail


def test_each_wheel_is_driven_alone_and_stopped_before_the_next() -> None:
    robot = FakeRobot()
    spin(robot)
    assert robot.calls == ["drive 0", "stop", "drive 1", "stop", "drive 2", "stop", "drive 3", "stop"]


def test_swapped_encoders_are_named_both_ways() -> None:
    findings = spin(FakeRobot(encoder_of=(2, 1, 0, 3)), seen="ffff")
    assert verdicts(findings) == [Verdict.FAIL, Verdict.PASS, Verdict.FAIL, Verdict.PASS]
    assert findings[0].detail == "rear_left encoder reads front_left's wheel"
    assert findings[2].detail == "front_left encoder reads rear_left's wheel"
    assert "swap the encoder cables of front_left and rear_left" in findings[0].fix


def test_a_reversed_motor_seen_turning_backward_is_named_with_its_fix() -> None:
    findings = spin(FakeRobot(motor_sign=(1, -1, 1, 1)), seen="fbff")
    assert verdicts(findings) == [Verdict.PASS, Verdict.FAIL, Verdict.PASS, Verdict.PASS]
    assert findings[1].detail.startswith("front_right motor reversed")
    assert findings[1].fix == "swap IN1/IN2 (GPIO 21, 26) or set motors.wheels.front_right.sign: -1"


def test_a_reversed_encoder_seen_turning_forward_is_named_with_its_fix() -> None:
    findings = spin(FakeRobot(encoder_sign=(1, 1, 1, -1)), seen="ffff")
    assert findings[3].detail.startswith("rear_right encoder reversed")
    assert findings[3].fix == "swap its A/B wires (GPIO 2, 3) or set encoders.wheels.rear_right.sign: -1"


def test_unwatched_a_backward_count_names_both_possible_causes() -> None:
    findings = spin(FakeRobot(motor_sign=(1, -1, 1, 1)))
    assert findings[1].verdict is Verdict.FAIL
    assert "its motor or its encoder is reversed" in findings[1].detail
    assert "motors.wheels.front_right.sign: -1" in findings[1].fix
    assert "encoders.wheels.front_right.sign: -1" in findings[1].fix


def test_motor_and_encoder_both_reversed_only_a_person_can_see() -> None:
    robot = FakeRobot(motor_sign=(-1, 1, 1, 1), encoder_sign=(-1, 1, 1, 1))
    assert spin(robot)[0].verdict is Verdict.PASS  # the encoder alone cannot tell
    findings = spin(FakeRobot(motor_sign=(-1, 1, 1, 1), encoder_sign=(-1, 1, 1, 1)), seen="bfff")
    assert findings[0].detail.startswith("front_left motor and encoder both reversed")


def test_a_dead_motor_and_a_dead_encoder_are_told_apart_by_the_person() -> None:
    findings = spin(FakeRobot(rate=(RATE, RATE, 0.0, RATE)))
    assert findings[2].detail.startswith("rear_left did not move")
    assert "enable GPIO 18, IN1 GPIO 23, IN2 GPIO 24" in findings[2].fix
    findings = spin(FakeRobot(encoder_sign=(1, 1, 0, 1)), seen="ffff")
    assert findings[2].detail == "rear_left turned but no encoder counted"
    assert "A on GPIO 5, B on GPIO 6" in findings[2].fix


def test_motor_pins_that_drive_another_wheel_are_named_when_the_person_saw_it_still() -> None:
    findings = spin(FakeRobot(motor_of=(2, 1, 0, 3)), seen="nfnf")
    assert findings[0].detail.startswith("front_left's motor pins drive rear_left's wheel")
    unwatched = spin(FakeRobot(motor_of=(2, 1, 0, 3)))
    assert "or front_left's motor pins drive rear_left's wheel" in unwatched[0].detail


def test_one_wheel_read_by_two_encoders_is_cross_wiring() -> None:
    findings = spin(FakeRobot(encoder_of=(0, 1, 0, 3)), seen="ffff")
    assert findings[0].detail == "driving front_left moved the encoders of front_left, rear_left"
    assert findings[2].detail.startswith("rear_left turned but no encoder counted")


@pytest.mark.parametrize(("factor", "verdict"), [(4.0, Verdict.FAIL), (1.6, Verdict.PASS), (0.25, Verdict.FAIL)])
def test_counts_per_turn_must_fit_the_configuration(factor: float, verdict: Verdict) -> None:
    """An encoder decoded x4 but configured x1 (or on the motor shaft) counts several times too fast."""
    findings = spin(FakeRobot(rate=(RATE * factor, RATE, RATE, RATE)))
    assert findings[0].verdict is verdict
    if verdict is Verdict.FAIL:
        assert findings[0].detail.startswith("front_left counts per turn implausible")
        assert "encoders.ppr (1700" in findings[0].fix


def test_the_speed_check_follows_the_configured_decoding() -> None:
    """Configured x1 (1700 counts a turn) while the wheel's encoder gives 6800: four times too fast."""
    x1 = parse("encoders: {decoding: x1}\n")
    findings = spin(FakeRobot(), config=x1)
    assert verdicts(findings) == [Verdict.FAIL] * 4
    assert "by 1700 counts a turn" in findings[0].detail


def test_the_motor_is_stopped_when_reading_the_encoders_fails() -> None:
    robot = FakeRobot()
    reads = 0

    def failing_counts() -> tuple[int, int, int, int]:
        nonlocal reads
        reads += 1
        if reads == 2:  # while the first wheel turns
            raise ConnectionResetError("pigpiod went away")
        return robot.counts()

    with pytest.raises(ConnectionResetError):
        asyncio.run(spin_wheels(robot, failing_counts, PLAN, sleep=robot.sleep, clock=robot.clock))
    assert robot.calls == ["drive 0", "stop"]
    assert robot.driven is None


def test_runs_record_what_every_encoder_did() -> None:
    robot = FakeRobot(encoder_of=(2, 1, 0, 3))
    runs = asyncio.run(spin_wheels(robot, robot.counts, PLAN, sleep=robot.sleep, clock=robot.clock))
    first: WheelRun = runs[0]
    assert first.moved[0] == 0
    assert first.moved[2] == round(RATE * (PLAN.ramp_s + PLAN.measure_s))
    assert first.rates[2] == pytest.approx(RATE, rel=1e-3)
    assert first.seen is Seen.UNSEEN
