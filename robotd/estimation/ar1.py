"""Correlated fix errors as an AR(1) (first-order Gauss-Markov) sequence: how correlated, what they are worth. Pure.

Fixes whose errors persist from one to the next (multipath, a wall's echo, a delay not yet learnt) carry less
information than as many independent ones; both the calibration's windows and the heading's fits measure that
correlation on their residuals and discount by it.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

MAX_CORRELATION = 0.98
MIN_CORRELATION_BEYOND_CHANCE = 2.0  # / sqrt(n): a sample correlation of n white residuals stays below it (2 sigma)


def lag_one_correlation(residual: npt.NDArray[np.float64], sigma2: float) -> float:
    """The correlation of consecutive residuals (n x 2, both axes) of per-axis variance sigma2, within [0, 0.98]."""
    if len(residual) < 3:
        return 0.0
    products = residual[1:, 0] * residual[:-1, 0] + residual[1:, 1] * residual[:-1, 1]
    rho = float(np.mean(products)) / (2.0 * sigma2)
    return min(max(rho, 0.0), MAX_CORRELATION)


def beyond_chance(rho: float, residuals: int) -> float:
    """rho when it exceeds what chance gives `residuals` independent ones (2 / sqrt(n)), else 0."""
    return rho if rho > MIN_CORRELATION_BEYOND_CHANCE / math.sqrt(max(residuals, 1)) else 0.0


def information(rho: float) -> float:
    """An AR(1) sequence of n values of lag-one correlation rho is worth n (1 - rho) / (1 + rho) independent ones."""
    return max((1.0 - rho) / (1.0 + rho), 0.02)


__all__ = ["beyond_chance", "information", "lag_one_correlation"]
