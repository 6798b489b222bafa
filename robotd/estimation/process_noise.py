"""The process noise learnt from the fixes: one scale on the configured odometry noise, the likeliest for a bank of
shadow filters that differ only in that scale and in the fix noise. Pure (numpy).

Theory of operation: the configured odometry noise (`odom_*_sigma_m`, `*_heading_sigma_rad`) is a prior for a typical
floor; a robot on a flat, grippy floor drifts far less, one on a rough floor more. A filter whose process noise is
right predicts each fix with the right uncertainty, so over a run of fixes its innovations are the likeliest: the
multiple-model estimate (Magill), the likelihood `robotd tune` maximises over whole logs, here online. Running
robotd's filter once per candidate would cost a filter each; instead each candidate is a shadow that rides on it: the
position alone, per axis (the two axes alike), moved by the same odometry, so it keeps only its offset from robotd's
position and its variance. Between two fixes a shadow's variance grows by what robotd's grew through the heading, the
scales and the rest (robotd's growth less its own position noise at the scale in use), plus the shadow's scale times
the configured position noise of the distance driven; at a fix it has its own innovation (robotd's less its offset),
gain and likelihood. The shadows also differ in the fix noise they assume, a grid about the noise at their start: a
fix noise estimate a little off would otherwise pass for process noise (too small a one makes every innovation look
like drift). The scale is the posterior mean of its log over the bank, with a log-normal prior about where it started
(PRIOR_SIGMA) and a memory of a few hundred fixes (FORGET), so that a floor that changes is followed.

It learns only from fixes the caller judges fit (independent, the heading known) and only when the robot moved since
the fix before: at rest the odometry adds no noise, and the shadows could not differ. The robotd filter before this
used the innovations' whiteness (Mehra). In a synthetic filter whose only error is the position's random walk both
find a hundredth of the prior as a few hundredths within 300 fixes; but robotd's innovations also persist while its
heading and scales are still being learnt, which the whiteness test reads as drift left unfollowed: on the flat-floor
virtual robot (config/sim-lab.yaml, square, seed 2) it took a whole loop to bring the scale down to a tenth (the
covariance twice as wide as the error meanwhile), while the shadows, which grow by robotd's own heading and scale
uncertainty, got there within 3 m of driving.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

LOG_SCALE_STEP = 0.5  # the bank's grid in log scale, bounds included: neighbours at most a factor 1.65 apart (the
# posterior mean lies between)
# the fix noise variances the shadows assume, as factors on the one at their start: up to 3.3x either way
LOG_FIX_NOISE_FACTORS = np.arange(-4, 5) * 0.3
# of the log scale about where it started: the configuration within a factor 4.5 at one sigma. Wider (3.0) let the
# rough floor's heading drift, not a random walk of the position, pull the scale below the honest one (config/sim.yaml
# seeds 4-9: 5 of 19 logs with the truth inside the 95 % ellipse less than 0.85 of the time); narrower (1.0) left
# flat floors' covariance wide for longer
PRIOR_SIGMA = 1.5
FIX_NOISE_PRIOR_SIGMA = 1.0  # of the log of the fix noise's factor: the estimate in use is usually close
FORGET = 0.995  # each learning fix's weight on the next: a memory of about 200 fixes (15-50 s of driving)
NIS_CAP = 13.8  # a fix's NIS (per shadow) counts at most as at the 0.999 gate: an outlier must not decide the scale
MIN_MOTION_M = 0.005  # no learning when the robot hardly moved since the fix before


class ProcessNoiseScale:
    """The multiplier of the configured odometry noise variances, within [low, high] (low <= 1 <= high, as the
    configuration requires), learnt from accepted fixes; `start` (bounded) until learnt: 1, the configuration itself,
    or what a run before learnt.

    `position_var_per_m`: the configured odometry noise's position variance per axis and metre driven, at scale 1.
    """

    def __init__(self, low: float, high: float, start: float = 1.0, *, position_var_per_m: float) -> None:
        self.low = low
        self.high = high
        self.value = min(max(start, low), high) if math.isfinite(start) else 1.0
        self.position_var_per_m = position_var_per_m
        span = math.log(high) - math.log(low)
        log_scales = np.linspace(math.log(low), math.log(high), max(math.ceil(span / LOG_SCALE_STEP), 1) + 1)
        grid_scale, grid_fix = np.meshgrid(log_scales, LOG_FIX_NOISE_FACTORS, indexing="ij")
        self._log_scale: FloatArray = grid_scale.ravel()
        self._scale: FloatArray = np.exp(self._log_scale)
        self._fix_factor: FloatArray = np.exp(grid_fix.ravel())
        self._log_fix_factor: FloatArray = grid_fix.ravel()
        self.learnt = 0  # fixes learnt from
        self._start_bank(self.value)

    def _start_bank(self, start: float) -> None:
        """The bank with nothing learnt: the prior about `start`, no shadows yet."""
        self._log_prior: FloatArray = -0.5 * (
            ((self._log_scale - math.log(start)) / PRIOR_SIGMA) ** 2
            + (self._log_fix_factor / FIX_NOISE_PRIOR_SIGMA) ** 2
        )
        self._log_likelihood: FloatArray = np.zeros_like(self._log_scale)
        self._fix_var: FloatArray | None = None  # each shadow's fix noise variance: a grid about the first fix's
        self.forget()

    def reset(self) -> bool:
        """Back to the prior, 1, forgetting what was learnt; returns whether the scale changed."""
        changed = self.value != 1.0
        self.value = 1.0
        self._start_bank(1.0)
        return changed

    def forget(self) -> None:
        """The shadows start afresh from robotd's filter at the next fix (a seed, a recovery or a rejected fix came
        between: the offsets were of a position that is no longer robotd's)."""
        n = len(self._scale)
        self._offset_x: FloatArray = np.zeros(n)
        self._offset_y: FloatArray = np.zeros(n)
        self._var: FloatArray | None = None  # each shadow's position variance per axis after the last fix
        self._filter_var = 0.0  # robotd's, after the last fix
        self._distance = 0.0

    def on_innovation(self, nu: tuple[float, float], s: float, r: float, distance: float, *, learn: bool) -> bool:
        """An accepted fix's innovation nu, with robotd's predicted variance per axis s of which r is the fix noise,
        at `distance` driven (the odometry's); learn only when `learn`. Returns whether the scale changed."""
        predicted = max(s - r, 0.0)  # robotd's position variance per axis before the fix
        gain = predicted / s  # robotd's, per axis (its 2x2 gain with the axes alike)
        after = predicted * (1.0 - gain)
        fix_var = self._fix_var
        if self._var is None or fix_var is None:  # the shadows start as robotd's filter is after this fix
            if fix_var is None:
                self._fix_var = r * self._fix_factor
            self._var = np.full(len(self._scale), after)
            self._filter_var, self._distance = after, distance
            return False
        driven = max(distance - self._distance, 0.0)
        self._distance = distance
        noise = self.position_var_per_m * driven
        # robotd's growth through the heading, the scales and the rest: its own, less its position noise at the
        # scale in use; every shadow grows by it, and by its own scale's position noise
        rest = max(predicted - self._filter_var - self.value * noise, 0.0)
        var = self._scale * noise
        var += self._var
        var += rest
        total = var + fix_var  # each shadow's S per axis
        nu_x = nu[0] - self._offset_x
        nu_y = nu[1] - self._offset_y
        changed = False
        if learn and driven >= MIN_MOTION_M:
            nis = nu_x * nu_x
            nis += nu_y * nu_y
            nis /= total
            np.minimum(nis, NIS_CAP, out=nis)
            log_likelihood = self._log_likelihood
            log_likelihood *= FORGET
            log_likelihood -= np.log(total)
            log_likelihood -= 0.5 * nis
            self.learnt += 1
            weight = log_likelihood + self._log_prior
            weight -= weight.max()
            np.exp(weight, out=weight)
            value = math.exp(float(np.dot(weight, self._log_scale)) / float(weight.sum()))
            value = min(max(value, self.low), self.high)
            changed = value != self.value
            self.value = value
        shadow_gain = var / total
        # each shadow moves by its own correction, robotd's by its own: the offset changes by the difference
        nu_x *= shadow_gain
        nu_x -= gain * nu[0]
        self._offset_x += nu_x
        nu_y *= shadow_gain
        nu_y -= gain * nu[1]
        self._offset_y += nu_y
        var -= var * shadow_gain
        self._var = var
        self._filter_var = after
        return changed


__all__ = ["ProcessNoiseScale"]
