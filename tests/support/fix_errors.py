"""Fix errors for the estimation tests: an AR(1) (first-order Gauss-Markov) sequence, as multipath makes them."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt


def ar1_errors(rng: np.random.Generator, n: int, rho: float, sigma: float) -> npt.NDArray[np.float64]:
    """n 2D errors of an AR(1) sequence of lag-one correlation rho and per-axis deviation sigma."""
    errors = np.zeros((n, 2))
    errors[0] = rng.normal(0.0, sigma, 2)
    for k in range(1, n):
        errors[k] = rho * errors[k - 1] + rng.normal(0.0, sigma * math.sqrt(1.0 - rho * rho), 2)
    return errors
