"""The uneven floor: how much of each wheel's rim speed becomes motion of the ground under it.

Theory of operation: a wheel's traction is the fraction of its rim speed that moves the body (1 = perfect grip,
0.98 = 2 % slip). It is the product of a per-wheel constant (tyre wear, roller friction, load: the robot's own
mismatch) and a smooth field over the floor (the floor's unevenness), the latter a sum of a few plane waves with
seeded random directions, wavelengths and phases, scaled to unit variance. The encoders count the wheel's turns
before slip, so traction is exactly what odometry cannot see: unequal traction left and right turns the robot
slowly while the wheels say it drives straight, the paper's failure mode.

Not modelled: traction that depends on speed, acceleration or load transfer; skidding at high acceleration.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class FloorParams:
    """The statistics of the floor and of the robot's wheels."""

    traction_mean: float = 0.97
    wheel_spread: float = 0.016
    floor_amplitude: float = 0.02
    floor_modes: int = 6
    wavelength_m: tuple[float, float] = (1.0, 4.0)
    lateral_efficiency: float = 0.97


@dataclass(frozen=True, slots=True)
class _Wave:
    kx: float
    ky: float
    phase: float


class Floor:
    """A seeded traction field: `traction(wheel, x, y)` for each wheel at a point of the world frame."""

    def __init__(self, params: FloorParams, seed: int) -> None:
        rng = random.Random(f"robotd-sim:{seed}:floor")
        self.params = params
        self.wheel_bias = tuple(1.0 + rng.gauss(0.0, params.wheel_spread) for _ in range(4))
        waves = []
        low, high = params.wavelength_m
        for _ in range(params.floor_modes):
            direction = rng.uniform(0.0, 2.0 * math.pi)
            wavelength = math.exp(rng.uniform(math.log(low), math.log(high)))  # as many long waves as short
            k = 2.0 * math.pi / wavelength
            waves.append(_Wave(k * math.cos(direction), k * math.sin(direction), rng.uniform(0.0, 2.0 * math.pi)))
        self._waves = tuple(waves)
        # A sum of n cosines with random phases has variance n/2: this scale gives the field unit variance.
        self._scale = params.floor_amplitude * math.sqrt(2.0 / params.floor_modes) if params.floor_modes else 0.0

    def unevenness(self, x: float, y: float) -> float:
        """The floor's relative traction change at (x, y): zero mean, standard deviation floor_amplitude."""
        cos = math.cos
        return self._scale * sum([cos(w.kx * x + w.ky * y + w.phase) for w in self._waves])

    def traction(self, wheel: int, x: float, y: float) -> float:
        """Traction of wheel (0..3, FL FR RL RR) standing at world point (x, y), kept within [0.05, 1.0]."""
        value = self.params.traction_mean * self.wheel_bias[wheel] * (1.0 + self.unevenness(x, y))
        return min(1.0, max(0.05, value))

    def tractions(self, points: list[tuple[float, float]]) -> tuple[float, float, float, float]:
        """`traction` of the four wheels at their four points (the physics' hot path)."""
        t = [self.traction(wheel, x, y) for wheel, (x, y) in enumerate(points)]
        return (t[0], t[1], t[2], t[3])


def perfect_floor() -> Floor:
    """A floor with perfect grip everywhere: the robot moves exactly as the kinematics say."""
    params = FloorParams(
        traction_mean=1.0, wheel_spread=0.0, floor_amplitude=0.0, floor_modes=0, lateral_efficiency=1.0
    )
    return Floor(params, seed=0)
