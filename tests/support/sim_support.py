"""Shared helpers of the virtual robot's tests: configurations and odometry computed independently of the code."""

from __future__ import annotations

import math
from typing import Any

from sim_logs import sim_config

from robotd.config.model import RobotdConfig
from robotd.kinematics import Geometry, forward
from robotd.logs.sensorlog import Event, Truth, Wheels


def perfect_config(**sim_overrides: Any) -> RobotdConfig:
    """The virtual robot on a perfect floor with identical motors and a noiseless, always-present beacon."""
    perfect: dict[str, Any] = {
        "traction_mean": 1.0,
        "traction_wheel_spread": 0.0,
        "floor_amplitude": 0.0,
        "lateral_efficiency": 1.0,
        "motor_gain_spread": 0.0,
        "ips_noise_m": 0.0,
        "ips_dropout_probability": 0.0,
        "ips_outage_rate_per_min": 0.0,
        "ips_outlier_burst_rate_per_min": 0.0,
    }
    perfect.update(sim_overrides)
    return sim_config(**perfect)


def odometry_errors(events: list[Event], geometry: Geometry, counts_per_rev: int) -> tuple[float, float]:
    """Largest position error (m) and heading error (rad) of dead reckoning from the wheel counts, against truth."""
    x = y = theta = 0.0
    previous: Wheels | None = None
    worst_position = worst_heading = 0.0
    for event in events:
        if isinstance(event, Wheels):
            if previous is not None:
                dt = event.t - previous.t
                speeds = [
                    (a - b) * 2.0 * math.pi / counts_per_rev / dt
                    for a, b in zip(event.ticks, previous.ticks, strict=True)
                ]
                twist = forward(geometry, (speeds[0], speeds[1], speeds[2], speeds[3]))
                c, s = math.cos(theta), math.sin(theta)  # dead reckoning, the paper's eq. 2
                x, y = x + (twist.vx * c - twist.vy * s) * dt, y + (twist.vx * s + twist.vy * c) * dt
                theta += twist.wz * dt
            previous = event
        elif isinstance(event, Truth) and previous is not None and previous.t == event.t:
            worst_position = max(worst_position, math.hypot(x - event.x, y - event.y))
            worst_heading = max(worst_heading, abs(theta - event.theta))
    return worst_position, worst_heading
