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

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Geometry:
    """Wheel radius and half-distances of a mecanum base, in metres."""

    wheel_radius_m: float = 0.046875
    lx_m: float = 0.135
    ly_m: float = 0.125


@dataclass(frozen=True, slots=True)
class Twist:
    """Body-frame velocity: vx, vy in m/s, wz in rad/s."""

    vx: float
    vy: float
    wz: float


def forward(geometry: Geometry, wheel_speeds: tuple[float, float, float, float]) -> Twist:
    """Body twist from wheel angular speeds (rad/s, wheel order FL FR RL RR): paper eq. 1. (Wheel turns in rad give
    the body's displacement over the same interval.)"""
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
