"""The `sim` section of robotd's configuration: the virtual robot's parameters (read by the simulator only).

Split from robotd.config.model because it is the largest section and the daemon never reads it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from robotd.config.schema import Check, in_range, non_negative, positive, setting


def _span(low: float, high: float) -> Check:
    """A (min, max) pair with low <= min <= max <= high."""

    def check(pair: tuple[float, float]) -> str | None:
        if not low <= pair[0] <= pair[1] <= high:
            return f"must be [min, max] with {low} <= min <= max <= {high}, got [{pair[0]}, {pair[1]}]"
        return None

    check.__doc__ = f"[min, max] within {low} and {high}."
    return check


@dataclass(frozen=True, slots=True)
class SimConfig:
    """The virtual robot (only read by the simulator, never by the daemon). Defaults: the paper's floor."""

    seed: int = setting(1, "Seed of every random process of the simulation.", non_negative)
    initial_pose: tuple[float, float, float] = setting(
        (0.0, 0.0, 0.0), "True starting pose: x (m), y (m), theta (rad)."
    )
    physics_rate_hz: float = setting(
        100.0,
        "Physics steps (and ground truth samples) per second; motors are solved exactly between steps.",
        in_range(100.0, 10_000.0),
    )
    teleop_rate_hz: float = setting(
        10.0, "Rate at which a scenario's remote control sends commands.", in_range(1.0, 100.0)
    )
    motor_max_speed_rad_s: float = setting(22.0, "Wheel speed a motor reaches at full duty (no load).", positive)
    motor_time_constant_s: float = setting(0.08, "First-order time constant of a motor's speed.", in_range(0.001, 5.0))
    motor_deadband: float = setting(0.06, "Duty magnitude below which a motor does not turn.", in_range(0.0, 0.9))
    motor_gain_spread: float = setting(
        0.03, "Standard deviation of the motors' relative gain mismatch (the wheel PID hides it).", in_range(0.0, 0.5)
    )
    traction_mean: float = setting(
        0.97, "Mean fraction of a wheel's rim speed that moves the ground (1 = no slip).", in_range(0.05, 1.0)
    )
    traction_wheel_spread: float = setting(
        0.016, "Standard deviation of each wheel's constant relative traction mismatch.", in_range(0.0, 0.5)
    )
    floor_amplitude: float = setting(
        0.02, "Standard deviation of the floor's relative traction variation (the uneven floor).", in_range(0.0, 0.5)
    )
    floor_modes: int = setting(
        6, "Number of random plane waves summed into the floor's traction field.", in_range(0, 64)
    )
    floor_wavelength_m: tuple[float, float] = setting(
        (1.0, 4.0), "Shortest and longest wavelength of the floor's traction waves.", _span(0.05, 1000.0)
    )
    lateral_efficiency: float = setting(
        0.97, "Fraction of the kinematic sideways speed the rollers deliver.", in_range(0.05, 1.0)
    )
    ips_rate_hz: float = setting(12.0, "Mean rate of the hedgehog's position packets.", in_range(0.1, 100.0))
    ips_interval_jitter: float = setting(
        0.1, "Relative standard deviation of the interval between packets.", in_range(0.0, 1.0)
    )
    ips_latency_s: tuple[float, float] = setting(
        (0.05, 0.15),
        "Range of the uniform latency from measurement to arrival (the time-shift field).",
        _span(0.0, 60.0),
    )
    ips_noise_m: float = setting(0.03, "Standard deviation of a fix's noise in x and in y.", non_negative)
    ips_noise_z_m: float = setting(0.05, "Standard deviation of a fix's noise in z.", non_negative)
    ips_height_m: float = setting(0.3, "Height of the hedgehog above the floor.", in_range(-100.0, 100.0))
    ips_dropout_probability: float = setting(
        0.03, "Probability that a packet says 'coordinates unavailable'.", in_range(0.0, 1.0)
    )
    ips_outage_rate_per_min: float = setting(0.5, "Mean number of outages (beacon lost) per minute.", non_negative)
    ips_outage_duration_s: tuple[float, float] = setting(
        (1.0, 5.0), "Range of an outage's uniform duration.", _span(0.0, 3600.0)
    )
    ips_outlier_burst_rate_per_min: float = setting(
        0.6, "Mean number of outlier bursts (echoes) per minute.", non_negative
    )
    ips_outlier_burst_duration_s: tuple[float, float] = setting(
        (0.5, 2.5), "Range of an outlier burst's uniform duration.", _span(0.0, 3600.0)
    )
    ips_outlier_m: tuple[float, float] = setting(
        (1.0, 4.6), "Range of the uniform distance by which a fix in a burst is thrown.", _span(0.0, 1000.0)
    )
    ips_frame: Literal["mm", "cm"] = setting(
        "mm", "Position frames: mm (code 0x0011, stationary beacons 0x0012) or cm (0x0001, 0x0002)."
    )
    hedgehog_address: int = setting(7, "Address of the simulated hedgehog.", in_range(0, 255))
    stationary_beacons: tuple[tuple[float, float, float], ...] = setting(
        ((-1.0, 1.0, 2.0), (4.0, 1.0, 2.0), (4.0, -4.0, 2.0), (-1.0, -4.0, 2.0)),
        "Positions (x, y, z in m) of the stationary beacons, addresses 1, 2, ...; sent every beacons_period_s.",
    )
    beacons_period_s: float = setting(10.0, "Period of the stationary beacons' frame.", in_range(0.1, 3600.0))
    scenario_speed_mps: float = setting(0.3, "Speed of a scenario's commands.", in_range(0.01, 5.0))
    square_side_m: float = setting(3.0, "Side of the square scenario (paper: 3 m).", positive)
    scenario_pause_s: float = setting(1.0, "Stop between the legs of a scenario.", non_negative)
    outage_s: float = setting(20.0, "Length of the outage scenario's beacon loss, centred on the run.", non_negative)
    record_path: str = setting(
        "", "robotd vhw writes ground truth and the ticks and fixes it produced here (a sensor log); '' disables it."
    )

    def __post_init__(self) -> None:
        if len(self.stationary_beacons) > 32:
            raise ValueError(f"stationary_beacons: at most 32 beacons, got {len(self.stationary_beacons)}")
