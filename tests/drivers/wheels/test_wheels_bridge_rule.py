"""The L298 bridge rule on every transition the motor outputs make, read from the virtual pigpiod's pin history, and
the pins left driven low (never floating inputs) when the outputs close."""

from __future__ import annotations

from drivers.pigpiod.protocol import Mode
from drivers.virtual.l298 import Channel, bridge_rule_violations
from drivers.virtual.pigpiod import VirtualPigpiod
from drivers.virtual.pins import PinWrite
from drivers.wheels.motors import GpiozeroMotors, enable_and_direction_pins, wheel_pins
from robotd.config.model import MotorsConfig, PigpiodConfig

MOTORS = MotorsConfig()
CHANNELS = [Channel(p.enable, p.in1, p.in2) for p in wheel_pins(MOTORS)]
ENABLES, DIRECTIONS = enable_and_direction_pins(MOTORS)

# Duties per wheel (FL, FR, RL, RR) as the inverse kinematics gives them for each motion.
FORWARD = (0.6, 0.6, 0.6, 0.6)
REVERSE = (-0.4, -0.4, -0.4, -0.4)
STOP = (0.0, 0.0, 0.0, 0.0)
LATERAL = (-0.5, 0.5, 0.5, -0.5)
ROTATE = (-0.3, 0.3, -0.3, 0.3)


def write(t: float, gpio: int, level: int, duty: float) -> PinWrite:
    return PinWrite(t, "socket", "WRITE", gpio, 1, level, duty)


def test_the_checker_flags_a_direction_change_under_a_live_enable_and_only_that() -> None:
    channel = Channel(12, 16, 20)
    safe = [write(0, 16, 1, 1.0), write(1, 12, 0, 0.5), write(2, 12, 0, 0.0), write(3, 16, 0, 0.0), write(4, 20, 1, 1)]
    assert bridge_rule_violations(safe, [channel]) == []
    unsafe = [write(0, 16, 1, 1.0), write(1, 12, 0, 0.5), write(2, 20, 0, 0.0), write(3, 16, 0, 0.0)]
    violations = bridge_rule_violations(unsafe, [channel])
    assert len(violations) == 1, "rewriting a pin to the level it has is no change"
    assert "set GPIO 16 to 0 while enable GPIO 12 was at duty 0.500" in violations[0]


def test_every_transition_of_a_drive_sequence_keeps_the_bridge_rule(server: VirtualPigpiod) -> None:
    with GpiozeroMotors(MOTORS, PigpiodConfig(port=server.port)) as motors:
        for duties in (FORWARD, REVERSE, STOP, LATERAL, ROTATE, FORWARD, LATERAL, STOP):
            motors.set_duties(duties)
        motors.set_duties(ROTATE)  # and the process ends while the robot turns
    history = server.pin_history()
    assert bridge_rule_violations(history, CHANNELS) == []
    direction_changes = [w for w in history if w.gpio in DIRECTIONS and w.command in ("BS1", "BC1")]
    assert len(direction_changes) > 8, "the sequence did not reverse the channels"


def test_closing_leaves_every_motor_pin_an_output_driven_low(server: VirtualPigpiod) -> None:
    motors = GpiozeroMotors(MOTORS, PigpiodConfig(port=server.port))
    motors.set_duties(LATERAL)
    motors.close()
    assert [(server.mode(gpio), server.level(gpio), server.pwm_duty(gpio)) for gpio in ENABLES + DIRECTIONS] == [
        (Mode.OUTPUT, 0, 0.0)
    ] * 12, "an input would let the L298's input float"
    last_writes = {w.gpio: w for w in server.pin_history()}
    assert all(last_writes[gpio].mode == Mode.OUTPUT for gpio in ENABLES + DIRECTIONS)
    assert bridge_rule_violations(server.pin_history(), CHANNELS) == []


def test_closing_after_pigpiod_vanished_does_not_raise(server: VirtualPigpiod) -> None:
    motors = GpiozeroMotors(MOTORS, PigpiodConfig(port=server.port))
    motors.set_duties(FORWARD)
    server.stop()
    motors.close()  # nothing can be driven any more; it must only say nothing and return
