"""Planar frames as REP-103/REP-105 draw them: poses (x, y, theta), their composition, quaternions, and the 95 %
covariance ellipse. Pure.

The tree the live view publishes is map -> odom -> base_link -> beacon: `odom -> base_link` is the odometry-only
pose (dead reckoning, continuous, drifting), `map -> odom` is the correction the filter makes of it
(`fused * odom^-1`), so that map -> base_link is the fused pose; `base_link -> beacon` is the hedgehog's lever arm.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

Pose2 = tuple[float, float, float]

CHI2_2DOF_95 = -2.0 * math.log(0.05)
"""The squared Mahalanobis radius holding 95 % of a 2-D Gaussian (chi-square with 2 dof: 5.991)."""
ELLIPSE_POINTS = 48


def yaw_quaternion(theta: float) -> tuple[float, float, float, float]:
    """The unit quaternion (x, y, z, w) of a rotation by theta about z."""
    return (0.0, 0.0, math.sin(0.5 * theta), math.cos(0.5 * theta))


def compose(a: Pose2, b: Pose2) -> Pose2:
    """a * b: the pose b (given in frame a) in a's parent frame."""
    ax, ay, ath = a
    bx, by, bth = b
    c, s = math.cos(ath), math.sin(ath)
    return (ax + c * bx - s * by, ay + s * bx + c * by, _wrap(ath + bth))


def inverse(a: Pose2) -> Pose2:
    """a^-1, so that compose(a, inverse(a)) is the identity."""
    ax, ay, ath = a
    c, s = math.cos(ath), math.sin(ath)
    return (-(c * ax + s * ay), s * ax - c * ay, _wrap(-ath))


def correction(fused: Pose2, odometry: Pose2) -> Pose2:
    """map -> odom: the transform that carries the odometry-only pose onto the fused one (fused * odometry^-1)."""
    return compose(fused, inverse(odometry))


def covariance_ellipse(
    center: tuple[float, float], cov: Sequence[float], points: int = ELLIPSE_POINTS
) -> list[tuple[float, float]]:
    """The closed outline (first point repeated last) of the 95 % region of the position whose 3x3 covariance
    (row-major, x y theta) is `cov`; a degenerate covariance draws a point or a line, never fails."""
    sxx, sxy, syy = cov[0], cov[1], cov[4]
    # eigenvalues of [[sxx, sxy], [sxy, syy]] in closed form; the major axis at angle phi
    mean, half_diff = 0.5 * (sxx + syy), 0.5 * (sxx - syy)
    radius = math.hypot(half_diff, sxy)
    major, minor = max(mean + radius, 0.0), max(mean - radius, 0.0)
    phi = 0.5 * math.atan2(2.0 * sxy, sxx - syy)
    a, b = math.sqrt(CHI2_2DOF_95 * major), math.sqrt(CHI2_2DOF_95 * minor)
    c, s = math.cos(phi), math.sin(phi)
    cx, cy = center
    outline = []
    for k in range(points + 1):
        angle = 2.0 * math.pi * (k % points) / points
        u, v = a * math.cos(angle), b * math.sin(angle)
        outline.append((cx + c * u - s * v, cy + s * u + c * v))
    return outline


def covariance_6x6(cov: Sequence[float]) -> list[float]:
    """A planar 3x3 covariance (x, y, theta) as ROS's 6x6 pose covariance (x, y, z, roll, pitch, yaw), row-major;
    the unobserved z, roll and pitch get zero."""
    index = (0, 1, None, None, None, 2)
    return [0.0 if i is None or j is None else float(cov[3 * i + j]) for i in index for j in index]


def _wrap(angle: float) -> float:
    return math.atan2(math.sin(angle), math.cos(angle))
