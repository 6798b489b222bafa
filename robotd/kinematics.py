"""Mecanum kinematics of the paper (eq. 1), its exact inverse, and encoder counts to wheel speeds.

Wheel order: front-left, front-right, rear-left, rear-right (the paper's w1..w4); body frame x forward, y left,
angles counter-clockwise. With k = lx + ly (the paper's lfr + lrl):

    vx = r/4 ( w1 + w2 + w3 + w4)          w1 = (vx - vy - k wz) / r
    vy = r/4 (-w1 + w2 + w3 - w4)          w2 = (vx + vy + k wz) / r
    wz = r/(4k) (-w1 + w2 - w3 + w4)       w3 = (vx + vy - k wz) / r
                                           w4 = (vx - vy + k wz) / r

The four wheels over-determine three body speeds: forward(inverse(twist)) == twist exactly, and
forward() is the least-squares body twist of any four wheel speeds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class Geometry:
    """Wheel radius and half-distances of a mecanum base, in metres."""

    wheel_radius_m: float = 0.046875
    lx_m: float = 0.135
    ly_m: float = 0.125

    @property
    def forward_matrix(self) -> FloatArray:
        """J in (vx, vy, wz) = J @ (w1, w2, w3, w4): the paper's eq. 1."""
        r, k = self.wheel_radius_m, self.lx_m + self.ly_m
        return (r / 4.0) * np.array(
            [[1.0, 1.0, 1.0, 1.0], [-1.0, 1.0, 1.0, -1.0], [-1.0 / k, 1.0 / k, -1.0 / k, 1.0 / k]]
        )

    @property
    def inverse_matrix(self) -> FloatArray:
        """J+ in (w1, w2, w3, w4) = J+ @ (vx, vy, wz): the exact inverse of eq. 1."""
        r, k = self.wheel_radius_m, self.lx_m + self.ly_m
        return (1.0 / r) * np.array([[1.0, -1.0, -k], [1.0, 1.0, k], [1.0, 1.0, -k], [1.0, -1.0, k]])


@dataclass(frozen=True, slots=True)
class Twist:
    """Body-frame velocity: vx, vy in m/s, wz in rad/s."""

    vx: float
    vy: float
    wz: float


def forward(geometry: Geometry, wheel_speeds: tuple[float, float, float, float]) -> Twist:
    """Body twist from wheel angular speeds (rad/s, wheel order FL FR RL RR): paper eq. 1."""
    w1, w2, w3, w4 = wheel_speeds
    r, k = geometry.wheel_radius_m, geometry.lx_m + geometry.ly_m
    return Twist(
        vx=r / 4.0 * (w1 + w2 + w3 + w4),
        vy=r / 4.0 * (-w1 + w2 + w3 - w4),
        wz=r / (4.0 * k) * (-w1 + w2 - w3 + w4),
    )


def inverse(geometry: Geometry, twist: Twist) -> tuple[float, float, float, float]:
    """Wheel angular speeds (rad/s, FL FR RL RR) that produce a body twist: the inverse of eq. 1."""
    r, k = geometry.wheel_radius_m, geometry.lx_m + geometry.ly_m
    return (
        (twist.vx - twist.vy - k * twist.wz) / r,
        (twist.vx + twist.vy + k * twist.wz) / r,
        (twist.vx + twist.vy - k * twist.wz) / r,
        (twist.vx - twist.vy + k * twist.wz) / r,
    )


def counts_to_radians(counts: float, counts_per_rev: int) -> float:
    """Wheel angle turned for a number of decoded encoder counts."""
    return counts * (2.0 * math.pi / counts_per_rev)


def dead_reckon(x: float, y: float, theta: float, twist: Twist, dt: float) -> tuple[float, float, float]:
    """One step of dead reckoning (paper eq. 2): the body twist rotated into the world frame over dt."""
    c, s = math.cos(theta), math.sin(theta)
    return (
        x + (twist.vx * c - twist.vy * s) * dt,
        y + (twist.vx * s + twist.vy * c) * dt,
        theta + twist.wz * dt,
    )
