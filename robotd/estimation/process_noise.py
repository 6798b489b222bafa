"""The process noise learnt from the fixes: two scales on the configured odometry noise, the position terms' and the
heading terms', the likeliest for a bank of shadow filters that differ only in those scales and in the fix noise.
Pure (numpy).

Theory of operation: the configured odometry noise (`odom_*_sigma_m`, `*_heading_sigma_rad`) is a prior for a typical
floor; a robot on a flat, grippy floor drifts far less, one on a rough floor more. A filter whose process noise is
right predicts each fix with the right uncertainty, so over a run of fixes its innovations are the likeliest: the
multiple-model estimate (Magill), the likelihood `robotd tune` maximises over whole logs, here online. Running
robotd's filter once per candidate would cost a filter each; instead each candidate is a shadow that rides on it:
the pose (x, y, heading) moved by the same odometry, so it keeps only its offset from robotd's pose and its own 3x3
covariance. Between two fixes a shadow's covariance is carried through the motion (a heading error turns the
displacement driven) and grows by what robotd's grew through the scales' uncertainty and the rest (robotd's growth
less its own odometry noise at the scales in use), plus the shadow's scales times the configured noise of the
distance driven and the angle turned; at a fix it has its own innovation (robotd's less its offset), gain and
likelihood. The shadows also differ in the fix noise they assume, a grid about the noise at their start: a fix noise
estimate a little off would otherwise pass for process noise (too small a one makes every innovation look like
drift). Each scale is the posterior mean of its log over the bank, with a log-normal prior about where it started
and a memory of a few hundred fixes (FORGET), so that a floor that changes is followed.

Why two scales: a flat floor's position noise is a tenth of the configured or less, while the heading may still
drift (unequal traction turns the robot steadily). With one scale for both, the position innovations took the
heading's noise down with the position's, and on a rough floor the heading then lagged a steady turn while claiming
to know it (config/sim.yaml outage 9: the truth inside its own 95 % ellipse 0.56 of the time over a 20 s outage).
The heading's own scale is learnt from the same innovations: a heading error shows as a drift across the direction
of travel that grows with the distance driven, which a position random walk does not.

It learns only from fixes the caller judges fit (independent, the heading known) and only when the robot moved since
the fix before: at rest the odometry adds no noise, and the shadows could not differ. The robotd filter before this
used the innovations' whiteness (Mehra). In a synthetic filter whose only error is the position's random walk both
find a hundredth of the prior as a few hundredths within 300 fixes; but robotd's innovations also persist while its
heading and scales are still being learnt, which the whiteness test reads as drift left unfollowed: on the flat-floor
virtual robot (config/sim-lab.yaml, square, seed 2) it took a whole loop to bring the scale down to a tenth (the
covariance twice as wide as the error meanwhile), while the shadows (then of the position alone, grown by robotd's
own heading and scale uncertainty) got there within 3 m of driving.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from robotd.estimation import ekf

FloatArray = npt.NDArray[np.float64]

# the grids in log scale, bounds included: the position scale's neighbours a factor 2.1 apart, the heading scale's 2.7
# (the posterior mean lies between). Finer grids (factors 1.65 and 2.1, with nine fix noises: 1053 shadows) gave
# RMSEs within 2 % (median 0.1 %) on the held-out virtual robots' logs at three times the cost per fix
LOG_SCALE_STEP = 0.75
LOG_HEADING_SCALE_STEP = 1.0
# the fix noise variances the shadows assume, as factors on the one at their start: up to 2.2x either way
LOG_FIX_NOISE_FACTORS = np.arange(-2, 3) * 0.4
# of the log position scale about where it started: the configuration within a factor 4.5 at one sigma. Wider (2.0,
# 3.0) took the rmse of the held-out virtual robots' logs 1-2 % lower but left the truth inside the 95 % ellipse
# 0.84 of the time on some (config/sim.yaml and config/sim-lab.yaml, seeds 4-9)
PRIOR_SIGMA = 1.5
# of the log heading scale: wider, as a floor's heading drift is known less well beforehand. At 1.0 the flat floor's
# rmse was 3 % higher than at 3.0 (its heading noise held near the rough floor's); at 5.0 a rough-floor log's truth
# fell to 0.85 inside its 95 % ellipse
HEADING_PRIOR_SIGMA = 3.0
FIX_NOISE_PRIOR_SIGMA = 1.0  # of the log of the fix noise's factor: the estimate in use is usually close
FORGET = 0.995  # each learning fix's weight on the next: a memory of about 200 fixes (15-50 s of driving)
NIS_CAP = 13.8  # a fix's NIS (per shadow) counts at most as at the 0.999 gate: an outlier must not decide the scale
MIN_MOTION_M = 0.005  # the robot at rest since the fix before when it moved less: no learning, the shadows restart


class OdometryNoise(NamedTuple):
    """The configured odometry noise at scale 1: position variance per axis and metre driven (m^2/m), heading
    variance per metre driven (rad^2/m) and per radian turned (rad^2/rad), position variance per axis and radian
    turned (m^2/rad)."""

    position_var_per_m: float
    heading_var_per_m: float
    heading_var_per_rad: float
    position_var_per_rad: float = 0.0


class Pose(NamedTuple):
    """robotd's filter at a fix: its pose and covariance (upper triangle: xx, xy, xt, yy, yt, tt)."""

    x: float
    y: float
    theta: float
    p: ekf.Cov


class Travel(NamedTuple):
    """Where the odometry stood at a fix: distance driven (m) and heading turned (rad) since it began."""

    distance: float
    turned: float


class ProcessNoiseScale:
    """The multipliers of the configured odometry noise variances, the position terms' (`value`) and the heading
    terms' (`heading_value`), within [low, high] (low <= 1 <= high, as the configuration requires), learnt from
    accepted fixes; `start` and `heading_start` (bounded) until learnt: 1, the configuration itself, or what a run
    before learnt."""

    def __init__(
        self, low: float, high: float, start: float = 1.0, heading_start: float = 1.0, *, noise: OdometryNoise
    ) -> None:
        self.low = low
        self.high = high
        self.value = self._bounded(start)
        self.heading_value = self._bounded(heading_start)
        self.noise = noise
        span = math.log(high) - math.log(low)
        grid_position, grid_heading, grid_fix = np.meshgrid(
            _grid(low, high, span / LOG_SCALE_STEP),
            _grid(low, high, span / LOG_HEADING_SCALE_STEP),
            LOG_FIX_NOISE_FACTORS,
            indexing="ij",
        )
        self._log_scales: FloatArray = np.stack([grid_position.ravel(), grid_heading.ravel()])  # (position, heading)
        self._log_fix_factor: FloatArray = grid_fix.ravel()
        # per shadow, rows 0-5: its covariance after the last fix (P's upper triangle); rows 6-8: its multipliers of
        # the noise added between two fixes (its scales, and 1 for robotd's growth through the scales' uncertainty and
        # the rest). One product of the carry (below) with it takes every shadow to the next fix
        self._shadows = np.empty((9, len(self._log_fix_factor)))
        self._shadows[6:8] = np.exp(self._log_scales)
        self._shadows[8] = 1.0
        self._fix_factor: FloatArray = np.exp(self._log_fix_factor)
        # the small matrices of each fix, filled in place: making them anew cost more than the bank's own arithmetic.
        # The carry's rows 0-5 map a shadow's column to its predicted P, [P -> F P F^T | growth per unit of each
        # factor]; rows 6-14 to U = P H^T and S - R of that P (_to_u_s times rows 0-5): one product, not four
        self._carry = np.zeros((15, 9))
        self._carry[:6, :6] = np.eye(6)
        self._turning = np.eye(3)  # F on the offsets
        self._to_u_s = _to_u_s()  # P -> (U = P H^T, S - R)
        self.learnt = 0  # fixes learnt from
        self._start_bank(self.value, self.heading_value)

    def _bounded(self, start: float) -> float:
        return min(max(start, self.low), self.high) if math.isfinite(start) else 1.0

    def _start_bank(self, start: float, heading_start: float) -> None:
        """The bank with nothing learnt: the prior about where the scales start, no shadows yet."""
        self._log_prior: FloatArray = -0.5 * (
            ((self._log_scales[0] - math.log(start)) / PRIOR_SIGMA) ** 2
            + ((self._log_scales[1] - math.log(heading_start)) / HEADING_PRIOR_SIGMA) ** 2
            + (self._log_fix_factor / FIX_NOISE_PRIOR_SIGMA) ** 2
        )
        self._log_likelihood: FloatArray = np.zeros_like(self._log_fix_factor)
        self._fix_var: FloatArray | None = None  # each shadow's fix noise variance: a grid about the first fix's
        # the bank as reset() leaves it: about 1 and nothing learnt (a reset at each fix of correlated ones is free)
        self._as_reset = start == 1.0 and heading_start == 1.0
        self.forget()

    def reset(self) -> bool:
        """Back to the prior, 1, forgetting what was learnt; returns whether a scale changed."""
        changed = self.value != 1.0 or self.heading_value != 1.0
        self.value = self.heading_value = 1.0
        if self._as_reset:
            self._fix_var = None
            self.forget()
        else:
            self._start_bank(1.0, 1.0)
        return changed

    def forget(self) -> None:
        """The shadows start afresh from robotd's filter at the next fix (a seed, a recovery or a rejected fix came
        between: the offsets were of a pose that is no longer robotd's)."""
        self._offset: FloatArray = np.zeros((3, 0))  # x, y, heading: each shadow's less robotd's (with _cov)
        # 6 x shadows: each shadow's covariance after the last fix; None: the shadows are robotd's filter then
        self._cov: FloatArray | None = None
        self._last: tuple[float, Pose, Travel] | None = None  # the last fix's time, robotd's pose after it, travel

    def on_fix(  # noqa: PLR0917 - robotd's filter before and after the fix, as the shadows need it
        self,
        t: float,
        inn: ekf.Innovation,
        r: float,
        prior: Pose,
        posterior: Pose,
        travel: Travel,
        *,
        learn: bool,
        freeze_heading: bool,
    ) -> bool:
        """An accepted fix at t with robotd's innovation `inn` (fix noise variance r), its pose before (prior) and
        after (posterior) the fix, and the odometry's travel; learn only when `learn`; the shadows leave their
        heading as it is when robotd's does (`freeze_heading`). Returns whether a scale changed."""
        last = self._last
        if self._fix_var is None:
            self._fix_var = r * self._fix_factor
        # the shadows start as robotd's filter is after this fix: the first, one measured before the last, or one
        # with the robot at rest since the last, where the odometry adds no noise and the shadows could not differ
        # (fused alike, they converge on robotd's position). They are made when the robot next moves, so a robot at
        # rest costs next to nothing
        if last is None or t <= last[0] or travel.distance - last[2].distance < MIN_MOTION_M:
            self._cov = None
            self._last = (t, posterior, travel)
            return False
        _, before, travel_before = last
        shadows = self._shadows
        if self._cov is None:  # every shadow as robotd's filter was after the last fix
            shadows[:6] = np.asarray(before.p, dtype=np.float64)[:, None]
            self._offset = np.zeros((3, len(self._log_fix_factor)))
        driven = travel.distance - travel_before.distance
        # the displacement since the last fix: a heading error there turns it (the motion's Jacobian in theta)
        dx, dy = prior.x - before.x, prior.y - before.y
        carry, turning = self._carry, self._turning
        motion_growth = carry[:6]
        _set_motion(motion_growth, dx, dy)
        turning[0, 2], turning[1, 2] = -dy, dx
        turned = abs(travel.turned - travel_before.turned)
        noise = self.noise
        position_q = noise.position_var_per_m * driven + noise.position_var_per_rad * turned
        heading_q = noise.heading_var_per_m * driven + noise.heading_var_per_rad * turned
        # per unit of each scale: the position's on x and y; the heading's, added evenly over the displacement, on the
        # heading and, through the displacement still to come (a third of it on average), on the position
        spread = (dy * dy / 3.0, -dx * dy / 3.0, -dy / 2.0, dx * dx / 3.0, dx / 2.0, 1.0)
        heading_growth = [g * heading_q for g in spread]
        motion_growth[0, 6] = motion_growth[3, 6] = position_q
        motion_growth[:, 7] = heading_growth
        # robotd's growth through the scales' uncertainty and the rest: its own (prior.p less F before.p F^T, the map
        # _set_motion filled), less its odometry noise at the scales in use; every shadow grows by it, and by its own
        # scales' odometry noise
        moved = (motion_growth[:, :6] @ before.p).tolist()
        position, heading_scale = position_q * self.value, self.heading_value
        rest = [p - m - g * heading_scale for p, m, g in zip(prior.p, moved, heading_growth, strict=True)]
        rest[0] -= position
        rest[3] -= position
        motion_growth[:, 8] = _covariance(rest)
        _with_lever_arm(self._to_u_s, inn.h02, inn.h12)
        np.matmul(self._to_u_s, motion_growth, out=carry[6:])
        carried = carry @ shadows
        offset = turning @ self._offset
        changed = False
        fix_var = self._fix_var
        update = _Update(carried, offset, inn, fix_var, freeze_heading=freeze_heading)
        if learn:
            self._as_reset = False
            log_likelihood = self._log_likelihood
            log_likelihood *= FORGET
            log_likelihood -= update.log_density()
            self.learnt += 1
            weight = log_likelihood + self._log_prior
            weight -= weight.max()
            np.exp(weight, out=weight)
            means = self._log_scales @ weight
            means /= weight.sum()
            value, heading_value = self._bounded(math.exp(means[0])), self._bounded(math.exp(means[1]))
            changed = value != self.value or heading_value != self.heading_value
            self.value, self.heading_value = value, heading_value
        # each shadow moves by its own correction, robotd's by its own: the offset changes by the difference
        offset += update.correction()
        offset[0] -= posterior.x - prior.x
        offset[1] -= posterior.y - prior.y
        offset[2] -= ekf.wrap_angle(posterior.theta - prior.theta)
        self._offset = offset
        self._cov = update.covariance(out=shadows[:6])
        self._last = (t, posterior, travel)
        return changed


def _grid(low: float, high: float, steps: float) -> FloatArray:
    """Log scales from low to high, bounds included, about `steps` apart."""
    return np.linspace(math.log(low), math.log(high), max(math.ceil(steps), 1) + 1)


def _set_motion(motion: FloatArray, dx: float, dy: float) -> None:
    """Fill `motion`'s first six columns (its identity already there) with the linear map P -> F P F^T on the upper
    triangle (xx, xy, xt, yy, yt, tt), F the Jacobian of a displacement (dx, dy) in the heading (eq. 6, over the whole
    interval)."""
    a, b = -dy, dx
    motion[0, 2], motion[0, 5] = 2.0 * a, a * a
    motion[1, 2], motion[1, 4], motion[1, 5] = b, a, a * b
    motion[2, 5] = a
    motion[3, 4], motion[3, 5] = 2.0 * b, b * b
    motion[4, 5] = b


def _covariance(p: list[float]) -> tuple[float, float, float, float, float, float]:
    """p (upper triangle) made a covariance: variances at least 0, correlations within +-1 (robotd's growth less the
    noise at the scales in use is one only up to the linearisation over the interval)."""
    xx, xy, xt, yy, yt, tt = p
    xx, yy, tt = max(xx, 0.0), max(yy, 0.0), max(tt, 0.0)

    def within(c: float, u: float, v: float) -> float:
        bound = math.sqrt(u * v)
        return min(max(c, -bound), bound)

    return xx, within(xy, xx, yy), within(xt, xx, tt), yy, within(yt, yy, tt), tt


def _to_u_s() -> FloatArray:
    """The map from P (upper triangle) to U = P H^T (its column for the fix's x over x, y, heading, then for its y)
    and S - R = H U (s00, s01, s11), for H = [[1, 0, h02], [0, 1, h12]]: the lever arm's entries are set per fix
    (_with_lever_arm)."""
    m = np.zeros((9, 6))
    m[0, 0] = m[1, 1] = m[2, 2] = 1.0  # u0 = (xx, xy, xt) + h02 (xt, yt, tt)
    m[3, 1] = m[4, 3] = m[5, 4] = 1.0  # u1 = (xy, yy, yt) + h12 (xt, yt, tt)
    m[6, 0] = m[7, 1] = m[8, 3] = 1.0  # S - R from P: xx, xy, yy plus the lever arm's terms
    return m


# P+ = P - K U^T on the upper triangle, entry (i, j) of the pose (x, y, heading): K's row i times U's row j, summed over
# the two measured axes (K and U stacked: the x column's rows 0-2, the y column's 3-5)
_ROWS = [0, 0, 0, 1, 1, 2]
_COLUMNS = [0, 1, 2, 1, 2, 2]
_GAIN_ROWS = np.array(_ROWS + [r + 3 for r in _ROWS])
_U_ROWS = np.array(_COLUMNS + [c + 3 for c in _COLUMNS])


def _with_lever_arm(to_u_s: FloatArray, h02: float, h12: float) -> None:
    """Set the lever arm's entries of _to_u_s's map (zero without one) for a fix whose H is [[1, 0, h02], [0, 1,
    h12]]."""
    to_u_s[0, 2] = to_u_s[1, 4] = to_u_s[2, 5] = h02
    to_u_s[3, 2] = to_u_s[4, 4] = to_u_s[5, 5] = h12
    to_u_s[6, 2], to_u_s[6, 5] = 2.0 * h02, h02 * h02
    to_u_s[7, 2], to_u_s[7, 4], to_u_s[7, 5] = h12, h02, h02 * h12
    to_u_s[8, 4], to_u_s[8, 5] = 2.0 * h12, h12 * h12


class _Update:
    """Every shadow's Kalman update at one fix: innovation, its covariance S = H P H^T + R, gain K = U S^-1 with
    U = P H^T, its heading row zero when the heading is frozen. Arrays are (rows, shadows); `carried` holds each
    shadow's predicted P (rows 0-5), U's two columns (6-8, 9-11) and S - R (12-14)."""

    def __init__(
        self, carried: FloatArray, offset: FloatArray, inn: ekf.Innovation, fix_var: FloatArray, *, freeze_heading: bool
    ) -> None:
        self.p = carried[:6]
        self.u = carried[6:12]  # U's column for the fix's x over (x, y, heading), then for its y
        u0, u1 = carried[6:9], carried[9:12]
        s = carried[12:15]  # S - R, made S in place (the carried rows are this fix's own)
        s[0] += fix_var
        s[2] += fix_var
        self.det: FloatArray = s[0] * s[2] - s[1] * s[1]
        # S^-1 = [[s11, -s01], [-s01, s00]] / det
        self.inverse = s / self.det
        inverse = self.inverse
        # each shadow's innovation: robotd's less its offset as the fix sees it
        h02, h12 = inn.h02, inn.h12
        nu_x: FloatArray = inn.nu_x - offset[0]
        nu_y: FloatArray = inn.nu_y - offset[1]
        if h02 or h12:
            nu_x -= h02 * offset[2]
            nu_y -= h12 * offset[2]
        self.nu_x, self.nu_y = nu_x, nu_y
        # K = U S^-1, one column per measured axis, stacked: rows 0-2 the x column's, 3-5 the y column's
        i00, i01, i11 = inverse
        k = np.empty((6, len(fix_var)))
        np.multiply(u0, i11, out=k[:3])
        k[:3] -= u1 * i01
        np.multiply(u1, i00, out=k[3:])
        k[3:] -= u0 * i01
        if freeze_heading:
            k[2] = 0.0
            k[5] = 0.0
        self.k = k

    def log_density(self) -> FloatArray:
        """-log of each shadow's likelihood of its innovation (2 dof, constants dropped; the NIS capped)."""
        i00, i01, i11 = self.inverse
        nu_x, nu_y = self.nu_x, self.nu_y
        nis: FloatArray = nu_x * nu_x * i11
        nis -= 2.0 * nu_x * nu_y * i01
        nis += nu_y * nu_y * i00
        np.minimum(nis, NIS_CAP, out=nis)
        nis += np.log(self.det)
        nis *= 0.5
        return nis

    def correction(self) -> FloatArray:
        """Each shadow's state correction K nu (3 x shadows)."""
        correction: FloatArray = self.k[:3] * self.nu_x
        correction += self.k[3:] * self.nu_y
        return correction

    def covariance(self, out: FloatArray) -> FloatArray:
        """Each shadow's covariance after the fix, written to `out` (6 x shadows): P - K U^T, which is also the Joseph
        form's for a frozen heading's gain (its position rows optimal, its heading row zero)."""
        products = np.take(self.k, _GAIN_ROWS, axis=0)
        products *= np.take(self.u, _U_ROWS, axis=0)
        np.subtract(self.p, products[:6], out=out)
        out -= products[6:]
        return out


__all__ = ["OdometryNoise", "Pose", "ProcessNoiseScale", "Travel"]
