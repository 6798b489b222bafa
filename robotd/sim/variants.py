"""Named scenarios of what real robots do and the configuration never says: the test data of self-calibration.

Each variant drives a base scenario (robotd.sim.scenarios) on a world that differs from the configuration the log
describes (meta.robot is the configured robot, the physics the true one), or writes the log as another kind of robot
would: fixes without a measurement time, body twists instead of wheel ticks, a differential-drive base. Draws are
seeded per variant, so a seed gives the same robot every time, and different seeds give different robots:

- `latency`: fixes carry no measurement time; their true delay is drawn in [0.03, 0.2] s (jitter +-5 ms).
- `geometry`: the true wheel radius and the true half-distances differ from the configuration by up to +-12 %.
- `slip`: mecanum rollers that deliver 80-90 % of the sideways motion, a rougher floor, unequal wheels.
- `twist`: the base reports its body twist at 20 Hz (through the configured kinematics) instead of wheel ticks.
- `diffdrive`: a differential-drive base (lx = 0: left wheels FL and RL, right FR and RR), driven forward and turning.
- `harsh`: outlier bursts four times as often, an 8 s outage mid-run, fixes without a measurement time.
- `heading`: the robot put down facing a direction drawn in [-pi, pi), replayed by a filter told nothing of it (the
  default `ekf.initial_sigma`: `replayed_with`), as a recorded robot is; the baselines' guess of 0 is then wrong too.
"""

from __future__ import annotations

import dataclasses
import math
import random
from collections.abc import Iterator
from dataclasses import dataclass

from robotd import kinematics
from robotd.config.model import EkfConfig, RobotdConfig
from robotd.logs.sensorlog import Event, IpsFix, TwistSample, Wheels
from robotd.sim.scenarios import Scenario, ScenarioParams, random_commands, random_teleop

VARIANTS = ("latency", "geometry", "slip", "twist", "diffdrive", "harsh", "heading")
TWIST_RATE_HZ = 20.0
DIFF_LX_M = 1e-3  # the physics' wheel points need a length; the log says 0


@dataclass(frozen=True, slots=True)
class VariantRun:
    """What a variant needs: the scenario, the true world's configuration, the configuration the log describes."""

    scenario: Scenario
    world: RobotdConfig
    described: RobotdConfig
    untimed_fixes: bool = False
    twist_only: bool = False


def _rng(name: str, seed: int) -> random.Random:
    return random.Random(f"robotd-sim:{seed}:variant:{name}")


def _random_diff(params: ScenarioParams, loops: int, seed: int) -> Scenario:
    """Random forward driving and turning, as a differential-drive base can (no sideways command)."""
    rng = random.Random(f"robotd-sim:{seed}:teleop-diff")
    return random_commands(params, loops, rng, "diffdrive", lateral=False, max_turn=0.8)


def build(name: str, config: RobotdConfig, params: ScenarioParams, loops: int, seed: int) -> VariantRun:
    """The variant called `name` (one of VARIANTS) of the configured robot."""
    rng = _rng(name, seed)
    sim, robot = config.sim, config.robot
    base = random_teleop(params, loops, seed)
    match name:
        case "latency":
            delay = rng.uniform(0.03, 0.2)
            world = dataclasses.replace(
                config, sim=dataclasses.replace(sim, ips_latency_s=(max(0.0, delay - 0.005), delay + 0.005))
            )
            return VariantRun(base, world, config, untimed_fixes=True)
        case "geometry":
            true_robot = dataclasses.replace(
                robot,
                wheel_radius_m=robot.wheel_radius_m * (1.0 + rng.uniform(-0.12, 0.12)),
                lx_m=robot.lx_m * (1.0 + rng.uniform(-0.12, 0.12)),
                ly_m=robot.ly_m * (1.0 + rng.uniform(-0.12, 0.12)),
            )
            return VariantRun(base, dataclasses.replace(config, robot=true_robot), config)
        case "slip":
            rough = dataclasses.replace(
                sim,
                lateral_efficiency=rng.uniform(0.8, 0.9),
                floor_amplitude=0.04,
                traction_wheel_spread=0.03,
            )
            return VariantRun(base, dataclasses.replace(config, sim=rough), config)
        case "twist":
            return VariantRun(base, config, config, twist_only=True)
        case "diffdrive":
            diff_robot = dataclasses.replace(robot, lx_m=DIFF_LX_M)
            world = dataclasses.replace(config, robot=diff_robot, sim=dataclasses.replace(sim, lateral_efficiency=0.05))
            described = dataclasses.replace(config, robot=dataclasses.replace(robot, lx_m=0.0))
            return VariantRun(_random_diff(params, loops, seed), world, described)
        case "harsh":
            middle = base.duration_s / 2.0
            harsh = dataclasses.replace(sim, ips_outlier_burst_rate_per_min=4.0 * sim.ips_outlier_burst_rate_per_min)
            scenario = Scenario("harsh", base.segments, ((middle - 4.0, middle + 4.0),))
            return VariantRun(scenario, dataclasses.replace(config, sim=harsh), config, untimed_fixes=True)
        case "heading":
            x, y, _ = sim.initial_pose
            facing = dataclasses.replace(sim, initial_pose=(x, y, rng.uniform(-math.pi, math.pi)))
            return VariantRun(base, dataclasses.replace(config, sim=facing), config)
    raise ValueError(f"unknown variant {name!r}; known: {', '.join(VARIANTS)}")


def replayed_with(name: str, config: RobotdConfig) -> RobotdConfig:
    """The configuration a scenario's or variant's log is replayed with: `config`, except that the `heading` variant's
    filter is told nothing of the heading (its initial sigma the default's, the heading unknown)."""
    if name != "heading":
        return config
    sx, sy, _ = config.ekf.initial_sigma
    unknown = (sx, sy, EkfConfig().initial_sigma[2])
    return dataclasses.replace(config, ekf=dataclasses.replace(config.ekf, initial_sigma=unknown))


def logged(run: VariantRun, events: Iterator[Event]) -> Iterator[Event]:
    """The world's events as the variant's robot logs them."""
    ticks_of = kinematics.Geometry(
        run.described.robot.wheel_radius_m, run.described.robot.lx_m, run.described.robot.ly_m
    )
    radians_per_count = 2.0 * math.pi / run.described.encoders.counts_per_rev
    period = 1.0 / TWIST_RATE_HZ
    previous: Wheels | None = None
    for event in events:
        if run.untimed_fixes and type(event) is IpsFix:
            yield IpsFix(event.t, event.x, event.y, event.z)
        elif run.twist_only and type(event) is Wheels:
            if previous is None:
                previous = event
                yield TwistSample(event.t, 0.0, 0.0, 0.0)
            elif math.floor(event.t / period + 1e-6) > math.floor(previous.t / period + 1e-6):
                k = radians_per_count / (event.t - previous.t)
                speeds = tuple((new - old) * k for new, old in zip(event.ticks, previous.ticks, strict=True))
                twist = kinematics.forward(ticks_of, (speeds[0], speeds[1], speeds[2], speeds[3]))
                previous = event
                yield TwistSample(event.t, twist.vx, twist.vy, twist.wz)
        else:
            yield event


__all__ = ["VARIANTS", "VariantRun", "build", "logged", "replayed_with"]
