"""Sensor logs with known truth from the virtual robot's offline simulator, as `robotd replay` reads them."""

from __future__ import annotations

import dataclasses
import io
from typing import Any

from paths import SIM_CONFIG

from robotd.config.model import RobotdConfig, load
from robotd.logs.sensorlog import SensorLog, parse_lines
from robotd.sim.offline import simulate


def sim_config(ips_offset_m: tuple[float, float] = (0.0, 0.0), **sim: Any) -> RobotdConfig:
    """config/sim.yaml with the beacon at `ips_offset_m` on the robot and some `sim` keys replaced."""
    config = load(SIM_CONFIG)
    robot = dataclasses.replace(config.robot, ips_offset_m=ips_offset_m)
    return dataclasses.replace(config, robot=robot, sim=dataclasses.replace(config.sim, **sim))


def simulated_text(config: RobotdConfig, seed: int, loops: int = 1, scenario: str = "square") -> str:
    """The sensor log `robotd simulate` writes for one run."""
    buffer = io.StringIO()
    simulate(config, scenario, seed, loops, buffer)
    return buffer.getvalue()


def simulated(config: RobotdConfig, seed: int, loops: int = 1, scenario: str = "square") -> SensorLog:
    """One run's sensor log, parsed as `robotd replay` reads it."""
    return parse_lines(simulated_text(config, seed, loops, scenario).splitlines())
