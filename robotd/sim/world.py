"""The virtual robot's models built from a configuration: one place, so offline and live runs share them exactly."""

from __future__ import annotations

from dataclasses import dataclass

from drivers.virtual.marvelmind import POSITION_CM, POSITION_MM
from robotd.config.model import RobotdConfig
from robotd.config.sim import SimConfig
from robotd.kinematics import Geometry
from robotd.sim.floor import Floor, FloorParams
from robotd.sim.ips import Hedgehog, IpsParams
from robotd.sim.physics import MotorParams, Motors, Pose, Robot
from robotd.sim.scenarios import Scenario, ScenarioParams


def geometry_of(config: RobotdConfig) -> Geometry:
    """The robot's geometry from the configuration."""
    r = config.robot
    return Geometry(wheel_radius_m=r.wheel_radius_m, lx_m=r.lx_m, ly_m=r.ly_m)


def floor_params(sim: SimConfig) -> FloorParams:
    """The floor's statistics from the configuration."""
    return FloorParams(
        traction_mean=sim.traction_mean,
        wheel_spread=sim.traction_wheel_spread,
        floor_amplitude=sim.floor_amplitude,
        floor_modes=sim.floor_modes,
        wavelength_m=sim.floor_wavelength_m,
        lateral_efficiency=sim.lateral_efficiency,
    )


def motor_params(sim: SimConfig) -> MotorParams:
    """The motors' parameters from the configuration."""
    return MotorParams(
        max_speed_rad_s=sim.motor_max_speed_rad_s,
        time_constant_s=sim.motor_time_constant_s,
        deadband=sim.motor_deadband,
        gain_spread=sim.motor_gain_spread,
    )


def ips_params(sim: SimConfig) -> IpsParams:
    """The hedgehog's error model from the configuration."""
    return IpsParams(
        rate_hz=sim.ips_rate_hz,
        interval_jitter=sim.ips_interval_jitter,
        latency_s=sim.ips_latency_s,
        noise_m=sim.ips_noise_m,
        noise_z_m=sim.ips_noise_z_m,
        height_m=sim.ips_height_m,
        dropout_probability=sim.ips_dropout_probability,
        outage_rate_per_min=sim.ips_outage_rate_per_min,
        outage_duration_s=sim.ips_outage_duration_s,
        outlier_burst_rate_per_min=sim.ips_outlier_burst_rate_per_min,
        outlier_burst_duration_s=sim.ips_outlier_burst_duration_s,
        outlier_m=sim.ips_outlier_m,
        frame_code=POSITION_MM if sim.ips_frame == "mm" else POSITION_CM,
        address=sim.hedgehog_address,
    )


def scenario_params(sim: SimConfig) -> ScenarioParams:
    """How the scenarios' operator drives."""
    return ScenarioParams(
        speed_mps=sim.scenario_speed_mps, side_m=sim.square_side_m, pause_s=sim.scenario_pause_s, outage_s=sim.outage_s
    )


@dataclass(slots=True)
class World:
    """The robot on its floor and the hedgehog watching it, seeded."""

    robot: Robot
    hedgehog: Hedgehog
    ips_offset_m: tuple[float, float]

    def beacon_xy(self) -> tuple[float, float]:
        """The hedgehog's true position now (the robot's centre plus the lever arm)."""
        return self.robot.body.beacon_position(self.ips_offset_m)


def build_world(config: RobotdConfig, seed: int, scenario: Scenario | None = None) -> World:
    """The seeded models of one run; the scenario's forced outages reach the hedgehog."""
    sim = config.sim
    floor = Floor(floor_params(sim), seed)
    motors = Motors(motor_params(sim), seed)
    robot = Robot(geometry_of(config), motors, floor, Pose(*sim.initial_pose))
    outages = scenario.outages if scenario is not None else ()
    hedgehog = Hedgehog(ips_params(sim), seed, forced_outages=outages)
    return World(robot, hedgehog, config.robot.ips_offset_m)
