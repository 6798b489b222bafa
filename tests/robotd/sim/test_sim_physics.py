"""The virtual robot's physics: motors, kinematics on a perfect floor, and the paper's drift on the default floor."""

from __future__ import annotations

import math

import pytest
from sim_logs import sim_config
from sim_support import odometry_errors, perfect_config

from robotd.kinematics import Geometry, Twist, inverse
from robotd.logs.sensorlog import Event, IpsFix, Truth
from robotd.sim.edges import wheel_edges
from robotd.sim.floor import Floor, FloorParams, perfect_floor
from robotd.sim.offline import run
from robotd.sim.physics import Body, MotorParams, Motors, Pose
from robotd.sim.scenarios import Scenario, Segment
from robotd.sim.scenarios import build as build_scenario
from robotd.sim.world import geometry_of, scenario_params


def _motors(**overrides: float) -> Motors:
    params = {"max_speed_rad_s": 20.0, "time_constant_s": 0.1, "deadband": 0.1, "gain_spread": 0.0}
    params.update(overrides)
    return Motors(MotorParams(**params), seed=1)


def test_a_motor_does_not_turn_inside_its_deadband() -> None:
    motors = _motors()
    assert motors.steady_speed(0, 0.1) == 0.0
    assert motors.steady_speed(0, -0.05) == 0.0
    assert motors.steady_speed(0, 0.55) == pytest.approx(10.0)
    assert motors.steady_speed(0, -0.55) == pytest.approx(-10.0)


def test_a_motor_saturates_at_full_duty() -> None:
    motors = _motors()
    assert motors.steady_speed(1, 1.0) == pytest.approx(20.0)
    assert motors.steady_speed(1, 3.0) == motors.steady_speed(1, 1.0)
    assert motors.steady_speed(1, -3.0) == pytest.approx(-20.0)


def test_a_motor_reaches_63_percent_of_its_step_after_one_time_constant() -> None:
    motors = _motors()
    motors.advance((1.0, 1.0, 1.0, 1.0), 0.1)
    assert motors.speeds[0] == pytest.approx(20.0 * (1.0 - math.exp(-1.0)))


def test_motor_steps_are_exact_whatever_their_length() -> None:
    one, many = _motors(), _motors()
    turned_once = one.advance((0.7, -0.4, 0.2, 1.0), 0.25)
    turned = [0.0] * 4
    for _ in range(250):
        for wheel, increment in enumerate(many.advance((0.7, -0.4, 0.2, 1.0), 0.001)):
            turned[wheel] += increment
    assert turned == pytest.approx(turned_once, rel=1e-9, abs=1e-12)
    assert many.speeds == pytest.approx(one.speeds, rel=1e-9)


@pytest.mark.parametrize(
    ("twist", "expected"),
    [
        (Twist(0.3, 0.0, 0.0), (0.3, 0.0, 0.0)),
        (Twist(0.0, -0.3, 0.0), (0.0, -0.3, 0.0)),
        (Twist(0.0, 0.0, 0.5), (0.0, 0.0, 0.5)),
    ],
    ids=["forward", "sideways", "rotation"],
)
def test_on_a_perfect_floor_wheel_turns_move_the_body_as_the_kinematics_say(
    twist: Twist, expected: tuple[float, float, float]
) -> None:
    geometry = Geometry()
    body = Body(geometry, perfect_floor(), Pose(0.0, 0.0, 0.0))
    speeds = inverse(geometry, twist)
    for _ in range(100):  # one second
        body.move((speeds[0] * 0.01, speeds[1] * 0.01, speeds[2] * 0.01, speeds[3] * 0.01))
    assert (body.x, body.y, body.theta) == pytest.approx(expected, abs=1e-12)


def test_unequal_traction_left_and_right_turns_a_robot_driving_straight() -> None:
    geometry = Geometry()
    floor = Floor(FloorParams(traction_mean=0.99, wheel_spread=0.0, floor_amplitude=0.0, floor_modes=0), seed=1)
    body = Body(geometry, floor, Pose(0.0, 0.0, 0.0))
    straight = inverse(geometry, Twist(0.3, 0.0, 0.0))
    assert body.tractions() == pytest.approx((0.99,) * 4)
    body.move(tuple(w * 0.01 for w in straight))  # type: ignore[arg-type]
    assert body.theta == 0.0
    floor.wheel_bias = (0.98, 1.0, 0.98, 1.0)  # the left wheels slip more
    body.move(tuple(w * 0.01 for w in straight))  # type: ignore[arg-type]
    assert body.theta > 0.0  # the right side travels further: the robot turns left (counter-clockwise)


def _run_segment(segment: Segment, **sim_overrides: object) -> list[Event]:
    config = perfect_config(**sim_overrides)
    scenario = Scenario("test", (Segment(0.5), segment, Segment(2.0)))
    return list(run(config, scenario, seed=1))


@pytest.mark.parametrize(
    ("segment", "expected"),
    [
        (Segment(5.0, vx=0.3), (1.5, 0.0, 0.0)),
        (Segment(5.0, vy=-0.3), (0.0, -1.5, 0.0)),
        (Segment(4.0, wz=0.5), (0.0, 0.0, 2.0)),
    ],
    ids=["forward", "sideways", "rotation"],
)
def test_teleop_commands_through_the_control_law_move_the_robot_as_commanded_on_a_perfect_floor(
    segment: Segment, expected: tuple[float, float, float]
) -> None:
    events = _run_segment(segment)
    final = [e for e in events if isinstance(e, Truth)][-1]
    # The commanded axis within 3 % (the wheel PID's integral lags a little behind each ramp), the others still.
    assert (final.x, final.y, final.theta) == pytest.approx(expected, rel=0.03, abs=0.005)
    config = perfect_config()
    position_error, heading_error = odometry_errors(events, geometry_of(config), config.encoders.counts_per_rev)
    assert position_error < 0.005  # no slip: the wheels' turns tell the whole truth, up to one count per step
    assert heading_error < 0.005


def test_on_the_default_floor_an_open_loop_square_drifts_in_heading_like_the_papers_fig_6a() -> None:
    config = sim_config()
    scenario = build_scenario("square", scenario_params(config.sim), loops=3, seed=1)
    events = list(run(config, scenario, seed=1))
    truth = [e for e in events if isinstance(e, Truth)]
    headings = [abs(e.theta) for e in truth]
    assert math.degrees(max(headings)) > 3.0  # the robot turns slowly although it was never told to turn
    corner = next(e for e in truth if e.t >= 2.0 + 10.0 + 0.5)  # after the first +x leg
    assert corner.x == pytest.approx(3.0, abs=0.35)  # roughly the commanded leg ...
    assert abs(corner.y) > 0.01  # ... but not a straight one
    position_error, _ = odometry_errors(events, geometry_of(config), config.encoders.counts_per_rev)
    assert 0.9 < position_error < 1.8  # the paper: odometry alone drifts to about 1.3 m


def test_on_the_default_floor_fixes_have_centimetre_noise_and_outliers_of_several_metres() -> None:
    config = sim_config()
    scenario = build_scenario("square", scenario_params(config.sim), loops=3, seed=1)
    events = list(run(config, scenario, seed=1))
    truth = {round(e.t * 100): e for e in events if isinstance(e, Truth)}
    errors = []
    for fix in (e for e in events if isinstance(e, IpsFix)):
        centre = truth[round(fix.t_meas * 100)]
        errors.append(math.hypot(fix.x - centre.x, fix.y - centre.y))
    errors.sort()
    assert errors[len(errors) // 2] < 0.06  # most fixes: a few centimetres (noise, and 5 ms of motion at most)
    assert 3.5 < errors[-1] < 4.8  # the paper: IPS errors up to 4.6 m


def test_edges_fall_where_the_wheel_angle_crosses_each_count() -> None:
    cpr = 6800
    step = 2.0 * math.pi / cpr
    ticks, counts = wheel_edges(0.5 * step, 10.5 * step, 1000, 2000, cpr)
    assert counts.tolist() == list(range(1, 11))
    assert ticks.tolist() == [1050 + 100 * i for i in range(10)]
    ticks, counts = wheel_edges(10.5 * step, 7.5 * step, 0, 300, cpr)  # backwards: 10 -> 9 -> 8 -> 7
    assert counts.tolist() == [9, 8, 7]
    assert ticks.tolist() == [50, 150, 250]
    ticks, counts = wheel_edges(0.2 * step, 0.7 * step, 0, 100, cpr)
    assert len(ticks) == len(counts) == 0


def test_a_figure_of_eight_turns_one_way_then_the_other() -> None:
    config = sim_config()
    scenario = build_scenario("figure8", scenario_params(config.sim), loops=1)
    truth = [e for e in run(config, scenario, seed=1) if isinstance(e, Truth)]
    peak = max(truth, key=lambda e: e.theta)
    assert peak.theta > 5.5  # about one turn counter-clockwise ...
    assert truth[-1].theta < 1.0  # ... then one clockwise
    assert math.hypot(truth[-1].x, truth[-1].y) < 0.6  # and back near the start, give or take the floor's drift
