"""Online calibration: the odometry's scales and the fixes' delay, learnt from the fixes. Pure (numpy, no I/O).

Theory of operation. Real robots are never configured exactly: the effective wheel radius differs from the datasheet,
mecanum rollers and floors change sideways and rotational motion, and a fix without a measurement time arrives an
unknown delay after it was measured. The parameters c = (kx, ky, kw, tau_u, tau_k) say how the odometry's body
twist (vx, vy, wz) is really (kx vx, ky vy, kw wz), and how late a fix is beyond its stated time: tau_u for fixes
without a measurement time (stated: their arrival; tau_u is the latency), tau_k for fixes with one (ideally 0: a
check of the stated time). They change slowly (a random walk) and stay within bounds.

They are estimated window by window of travel (`window_m`), as a sequential Bayesian estimate: each window's data
are the odometry steps (raw twists) and the fixes accepted by the gate; the model of fix i, stated at s_i, is

    z_i = T + R(phi) b(s_i - tau),   b(t) = the beacon's position on the odometry path integrated from the window's
                                            start with twists (kx vx, ky vy, kw wz) and a heading drift psi per metre

where T, phi (the window's placement in the world) and psi (unequal traction) are nuisance parameters of the window.
The fit is Gauss-Newton on the fixes' residuals plus the prior of c from the windows before; the posterior of c is the
next prior. The residuals' noise is the fixes' (the residuals' own spread) and the odometry's own random error over
the window (`odometry_noise`, the filter's model of it), which acts as a random error of the window's scales: a
window cannot know a scale better than its own odometry lets it (_normal_equations). Why windows and not the filter's
innovations: the filter absorbs a wrong latency into a position offset at constant velocity, and a wrong scale into
an innovation bias along the velocity, so innovations confound the two; a window's whole path separates them (scale
stretches the path, delay shifts it along time, visible wherever the speed changes). Windows are disjoint, so no
fix is counted twice. Until the first window closes, the window so far is fitted every tenth of its travel and that
fit is the calibration in use (not committed: the closed window's fit starts from the same prior), so a robot does
not predict with the prior's uncertainty for the first window's whole length.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from robotd.estimation.ar1 import beyond_chance, information, lag_one_correlation
from robotd.estimation.heading import fit_rotation

FloatArray = npt.NDArray[np.float64]

N_CAL = 5  # kx, ky, kw, tau_u, tau_k
KX, KY, KW, TAU_U, TAU_K = range(N_CAL)
N_NUISANCE = 4  # phi, tx, ty, psi
MIN_FIXES = 12
# A window moves the calibration only when its fixes are worth this many independent ones (five per parameter of
# the fit's nine: the lag-one correlation that discounts them is itself estimated from a few dozen residuals)
MIN_INDEPENDENT_FIXES = 24
# A window closes once it has travelled window_m and holds this many fixes: a slow beacon (4 Hz) puts fewer than
# MIN_INDEPENDENT_FIXES on 1.5 m of travel, and a window that closed then would never move the calibration; a quarter
# more than needed covers the fixes that the fit trims or that fall after the window's end
FIXES_TO_CLOSE = MIN_INDEPENDENT_FIXES * 5 // 4
PSI_SIGMA = 0.05  # rad per metre: heading drift from unequal traction, the prior of the window's psi
SCALE_WALK = 0.01**2 / 60.0  # variance per second: a scale drifts about 1 % a minute at most
LATENCY_WALK = 0.005**2 / 60.0  # s^2 per second: a delay drifts about 5 ms a minute at most
# before the first window closes, the window so far is fitted each time it has travelled this share of a window more
# (Calibrator._interim): a few fits, not one per fix (a fit costs milliseconds on a Pi)
INTERIM_SHARE = 0.1
MAX_WINDOW_S = 60.0  # a window that has not travelled its length by then starts again (bounded memory)
TRIM_SIGMAS = 4.0
# Gauss-Newton stops after a step this small in every parameter of c: each step was about 1/50 of the one before on
# the virtual robot's windows, so what is left is some 2e-5, a hundredth of the smallest sigma a window reaches (a
# tenth of a percent of a scale, 5 ms of a delay); 1e-5 cost a fourth fit of the path in most windows
STEP_TOLERANCE = 1e-3
PLACEMENT_DOF = 2.0  # per axis: the window's placement (tx, ty, phi, psi) fitted to the fixes absorbs that much error
# A configured robot's three scales share one error, the wheel radius's (it scales every wheel speed, so vx, vy and wz
# alike), besides each one's own (rollers for vy, the track and slip for wz): the prior's share of the shared one in
# each scale's variance. Even odds between the two: a scale learnt then says half of what it found about the others
RADIUS_SHARE = 0.5


@dataclass(frozen=True, slots=True)
class Calibration:
    """The odometry scales (vx, vy, wz multipliers), the fixes' delays and their standard deviations."""

    kx: float = 1.0
    ky: float = 1.0
    kw: float = 1.0
    latency_s: float = 0.05  # of fixes without a measurement time
    time_error_s: float = 0.0  # of fixes with one: the check of their stated time
    sigmas: tuple[float, float, float, float, float] = (0.1, 0.1, 0.1, 0.1, 0.05)
    windows: int = 0  # windows fitted so far
    fix_correlated_var: float = 0.0  # m^2 per axis: the part of the fixes' error that persists from fix to fix
    fix_correlation: float = 0.0  # lag-one correlation of consecutive fixes' errors (0: independent fixes)
    fix_var: float = 0.0  # m^2 per axis: the fixes' error variance that the fits judging them saw (smoothed)

    @property
    def fix_information(self) -> float:
        """What one fix is worth against an independent one: (1 - rho) / (1 + rho), the AR(1) discount."""
        return information(self.fix_correlation)

    @property
    def wheel_radius_scale(self) -> float:
        """The effective wheel radius over the configured one (the forward scale)."""
        return self.kx

    @property
    def lateral_scale(self) -> float:
        """Sideways motion over what the wheels' kinematics give, beyond the radius scale (mecanum rollers)."""
        return self.ky / self.kx

    @property
    def rotation_scale(self) -> float:
        """Rotation over what the kinematics give, beyond the radius scale (track, wheel scrub)."""
        return self.kw / self.kx

    @property
    def persistent_fix_var(self) -> float:
        """The fixes' error variance per axis when the fits found it persisting from fix to fix, else 0.

        Innovations see only the part of a persistent error that changes between fixes (the filter has followed the
        rest), so they cannot measure that noise: the fits, whose odometry path does not follow the fixes, can.
        """
        return self.fix_var if self.fix_correlation > 0.0 else 0.0

    def as_dict(self) -> dict[str, float | int]:
        """The status's and replay's report."""
        s = self.sigmas
        return {
            "wheel_radius_scale": round(self.kx, 5),
            "wheel_radius_scale_sigma": round(s[KX], 5),
            "lateral_scale": round(self.lateral_scale, 5),
            "lateral_scale_sigma": round(math.hypot(s[KY], s[KX]), 5),
            "rotation_scale": round(self.rotation_scale, 5),
            "rotation_scale_sigma": round(math.hypot(s[KW], s[KX]), 5),
            "latency_s": round(self.latency_s, 5),
            "latency_sigma_s": round(s[TAU_U], 5),
            "time_error_s": round(self.time_error_s, 5),
            "time_error_sigma_s": round(s[TAU_K], 5),
            "fix_correlated_sigma_m": round(math.sqrt(self.fix_correlated_var), 5),
            "fix_correlation": round(self.fix_correlation, 5),
            "windows": self.windows,
        }


@dataclass(frozen=True, slots=True)
class CalibrationLimits:
    """Bounds and priors: scales within 1 +- scale_limit, delays within [0, latency_max_s] (the check within +-)."""

    scale_limit: float = 0.25
    latency_max_s: float = 0.5
    window_m: float = 1.5


class Calibrator:
    """The sequential window estimate of Calibration (see the module docstring)."""

    def __init__(self, start: Calibration, limits: CalibrationLimits, offset: tuple[float, float]) -> None:
        self.limits = limits
        self.offset = offset
        self.mean = np.array([start.kx, start.ky, start.kw, start.latency_s, start.time_error_s])
        self.cov = np.diag(np.square(np.asarray(start.sigmas, dtype=np.float64)))
        if not start.windows:  # the configuration's prior (a saved calibration's covariance is its fits')
            scales = np.asarray(start.sigmas[:3], dtype=np.float64)
            shared = RADIUS_SHARE * np.outer(scales, scales)
            np.fill_diagonal(shared, 0.0)
            self.cov[:3, :3] += shared
        self.windows = start.windows
        self.fix_correlated_var = start.fix_correlated_var
        self.fix_correlation = start.fix_correlation
        self.fix_var = start.fix_var
        # of the residuals of each window's fit on its data alone, smoothed; a saved judgement's correlation until
        # this run's windows say otherwise (0 would let the first window after a restart fit correlated fixes)
        self._data_correlation = start.fix_correlation
        self._heading_judged = False  # judge_fixes has judged the fixes (before any window)
        self._fitted_at = math.nan
        # the odometry's own random error as the filter models it (robotd.estimation.ekf.ControlNoise's lin2, lat2,
        # slip2, turn2: the configured noise times the learnt scales); 0 takes a window's path as exact but for c
        self.odometry_noise: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
        self._clamp()
        self.current = self._snapshot()
        self._start_window(math.nan)

    # --- data -------------------------------------------------------------------------------------------

    def _start_window(self, t: float, fixes: list[tuple[float, float, float, bool]] | None = None) -> None:
        self._t0 = t
        self._steps_t: list[float] = []
        self._steps_dt: list[float] = []
        self._steps_u: list[tuple[float, float, float]] = []
        self._fixes: list[tuple[float, float, float, bool]] = fixes or []
        self.travel = 0.0
        self._interim_at = self.limits.window_m * INTERIM_SHARE  # the travel of the next interim fit

    def _delay(self, timed: bool) -> float:
        return float(self.mean[TAU_K] if timed else self.mean[TAU_U])

    def on_step(self, t_start: float, t_end: float, u: tuple[float, float, float]) -> None:
        """A prediction step over (t_start, t_end] with the raw odometry twist u."""
        last = self._steps_t[-1] if self._steps_t else self._t0
        if t_start != last or t_end - self._t0 > MAX_WINDOW_S:
            self._start_window(t_start)  # the first step, a gap in the steps, or a window that never ends
        self._steps_t.append(t_end)
        self._steps_dt.append(t_end - t_start)
        self._steps_u.append(u)
        self.travel += math.hypot(u[0], u[1]) * (t_end - t_start)

    def on_fix(self, stated_t: float, zx: float, zy: float, *, timed: bool) -> bool:
        """An accepted fix stated at stated_t (its measurement time when `timed`, else its arrival); returns True when
        `current` changed: a window closed and its fit was taken, or before the first one an interim fit was."""
        if math.isnan(self._t0) or stated_t - self._delay(timed) < self._t0:
            return False
        self._fixes.append((stated_t, zx, zy, timed))
        if self.travel < self.limits.window_m or len(self._fixes) < FIXES_TO_CLOSE or not self._steps_t:
            if self.windows or self.travel < self._interim_at or len(self._fixes) < MIN_INDEPENDENT_FIXES:
                return False
            self._interim_at = self.travel + self.limits.window_m * INTERIM_SHARE
            return self._interim()
        end = self._steps_t[-1]
        # the fixes measured on this window's path; those measured after its end start the next window
        inside = self._measured_by(end)
        later = [f for f in self._fixes if f[0] - self._delay(f[3]) > end]
        t0, ends = self._t0, np.array(self._steps_t)
        dts, us = np.array(self._steps_dt), np.array(self._steps_u)
        self._start_window(end, later)
        if len(inside) < MIN_FIXES:
            return False
        changed = self._commit(self._solve(t0, ends, dts, us, inside), float(ends[-1]))
        self.current = self._snapshot()
        return changed

    def _measured_by(self, end: float) -> list[tuple[float, float, float, bool]]:
        """The window's fixes measured by `end` (their stated time less their delay)."""
        return [f for f in self._fixes if f[0] - self._delay(f[3]) <= end]

    @property
    def judged(self) -> bool:
        """Whether the fixes' correlation is known: a window (this run's, or a saved calibration's), or judge_fixes."""
        return self.windows > 0 or self._heading_judged

    def judge_fixes(self, count: int, variance: float, correlation: float) -> bool:
        """An early judgement of the fixes from a shorter fit (the heading's window: `count` residuals of `variance`
        per axis and lag-one `correlation`), taken only before the first window; returns whether it was taken.

        Until a window has judged the fixes, a shared error among them looks like their agreement; heading fits come
        sooner, and the first window replaces what they say. A shared error once found stays found until then: a
        later fit whose few dozen residuals show no correlation beyond chance has not shown it gone (chance hides it).
        """
        if self.windows:
            return False
        rho = beyond_chance(correlation, count)
        if self._heading_judged and rho < self.fix_correlation:
            return False
        self._heading_judged = True
        self.fix_correlation = rho
        self.fix_correlated_var = variance * rho
        self.fix_var = variance
        # the scales and delays in use stay as they are (an interim fit's, or the prior)
        self.current = replace(
            self.current, fix_correlated_var=self.fix_correlated_var, fix_correlation=rho, fix_var=variance
        )
        return True

    # --- estimate ---------------------------------------------------------------------------------------

    def _walk_var(self, t: float) -> FloatArray:
        """The parameters' variances added by their random walk from the last fit to t."""
        dt = t - self._fitted_at if not math.isnan(self._fitted_at) and t > self._fitted_at else 0.0
        return np.diag(np.array([SCALE_WALK, SCALE_WALK, SCALE_WALK, LATENCY_WALK, LATENCY_WALK]) * dt)

    def _solve(
        self,
        t0: float,
        ends: FloatArray,
        dts: FloatArray,
        us: FloatArray,
        fixes: list[tuple[float, float, float, bool]],
    ) -> _WindowFit | None:
        """One window's Gauss-Newton fit with the committed prior walked to the window's end; None when it decided
        nothing. Pure: the calibration is not changed (_commit commits, _interim only reports)."""
        prior_cov = self.cov + self._walk_var(float(ends[-1]))
        stated = np.array([f[0] for f in fixes])
        zs = np.array([[f[1], f[2]] for f in fixes])
        timed = np.array([f[3] for f in fixes])
        path = _Path(t0, ends, dts, us, self.offset)
        prior_mean, prior_info = self.mean.copy(), np.linalg.inv(prior_cov)
        cal = self.mean.copy()
        bx, by = path.beacon(cal, 0.0, _measured(stated, timed, cal))
        phi, tx, ty = fit_rotation(bx.tolist(), by.tolist(), zs[:, 0].tolist(), zs[:, 1].tolist())
        nuisance = np.array([phi, tx, ty, 0.0])
        keep = np.ones(len(fixes), dtype=bool)
        info = prior_info
        sigma2 = rho = 0.0
        scale_var = self._window_scale_var(path)
        for _ in range(4):
            params = np.concatenate([nuisance, cal])
            residual, jac = _residuals_and_jacobian(path, params, stated, timed, zs)
            # the fixes' noise and correlation are judged on the residuals less the window's own odometry error (a
            # smooth deformation of the path, which would pass for correlated fixes)
            judged = residual - _odometry_error(jac, residual, keep, scale_var)
            sq = judged[:, 0] ** 2 + judged[:, 1] ** 2
            # the fix noise per axis: the residuals' robust spread (a median of chi-square 2 dof is 2 ln 2 sigma^2)
            sigma2 = max(float(np.median(sq[keep])) / (2.0 * math.log(2.0)), 1e-6)
            keep = sq <= (TRIM_SIGMAS**2) * 2.0 * sigma2
            if keep.sum() < MIN_FIXES:
                return None
            rho = lag_one_correlation(judged[keep], sigma2)
            # correlated fix errors (multipath, a wall's echo) carry less information than as many independent ones:
            # an AR(1) sequence of n values is worth n (1 - rho) / (1 + rho) independent ones
            weight = information(rho) / sigma2
            r = residual[keep].reshape(-1)
            j = jac[keep].reshape(-1, N_NUISANCE + N_CAL)
            a, g = _normal_equations(j, r, 1.0 / weight, scale_var)
            a[N_NUISANCE:, N_NUISANCE:] += prior_info
            g[N_NUISANCE:] -= prior_info @ (cal - prior_mean)
            a[3, 3] += 1.0 / PSI_SIGMA**2
            g[3] -= nuisance[3] / PSI_SIGMA**2
            a[0, 0] += 1e-9  # the placement is free; this only keeps the matrix invertible
            a[1, 1] += 1e-9
            a[2, 2] += 1e-9
            try:
                step = np.linalg.solve(a, g)
            except np.linalg.LinAlgError:
                return None
            nuisance = nuisance + step[:N_NUISANCE]
            cal = cal + step[N_NUISANCE:]
            info = a
            if float(np.max(np.abs(step[N_NUISANCE:]))) < STEP_TOLERANCE:
                break
        if not np.all(np.isfinite(cal)):
            return None
        n = int(keep.sum())
        # the residuals are the fixes' error less what the window's placement absorbed: an unbiased variance divides
        # by the fixes' worth less the placement's degrees of freedom (n - p); with errors that persist the fixes are
        # worth n (1 - rho) / (1 + rho), so the placement absorbs most of a shared error (a real UWB's, rho 0.87: the
        # residuals put its noise at 40 % of the truth) - at most a factor of 3, for a window worth few fixes
        worth = n * information(rho)
        sigma2 *= worth / max(worth - PLACEMENT_DOF, worth / 3.0)
        data_rho = _data_correlation(path, np.concatenate([nuisance, cal]), stated, timed, zs, keep)
        covariance = np.linalg.inv(info)[N_NUISANCE:, N_NUISANCE:]
        return _WindowFit(cal, 0.5 * (covariance + covariance.T), prior_cov, n, sigma2, rho, data_rho)

    def _window_scale_var(self, path: _Path) -> FloatArray:
        """The variances of (kx, ky, kw) that the odometry's own random error over the window amounts to: its error
        along and across (lin2, lat2 per metre of path) over the distance driven along each body axis, and its
        heading's (slip2 per metre, turn2 per radian) over the angle turned; at most 1 (a scale the window barely
        exercises)."""
        lin2, lat2, slip2, turn2 = self.odometry_noise
        along = float(np.abs(path.us[:, 0]) @ path.dts)
        across = float(np.abs(path.us[:, 1]) @ path.dts)
        turned = float(np.abs(path.us[:, 2]) @ path.dts)
        driven = float(path.step_dist.sum())
        return np.array(
            [
                _relative_var(lin2 * driven, along),
                _relative_var(lat2 * driven, across),
                _relative_var(slip2 * driven + turn2 * turned, turned),
            ]
        )

    def _commit(self, fit: _WindowFit | None, end: float) -> bool:
        """A closed window's fit (ending at `end`) committed: updates mean and cov and the judgement of the fixes;
        False when it decided nothing (no fit)."""
        if fit is None:
            return False
        self.cov = fit.prior_cov  # the random walk since the last fit
        self._fitted_at = end
        n = fit.fixes
        # what fusing many fixes cannot average away: their error shared from one fix to the next (smoothed)
        # (only a correlation beyond chance, 2 / sqrt(n): the path's own small deformations by slip are not the fixes')
        persistent = beyond_chance(fit.correlation, n)
        correlated = fit.fix_var * persistent
        smoothing = 1.0 if self.windows == 0 else 0.3
        self.fix_correlated_var += (correlated - self.fix_correlated_var) * smoothing
        self.fix_correlation += (persistent - self.fix_correlation) * smoothing
        self.fix_var += (fit.fix_var - self.fix_var) * smoothing
        self.windows += 1
        # the fixes' correlation is the installation's (anchors, walls), not one window's: judged over the windows
        self._data_correlation += (fit.data_correlation - self._data_correlation) * smoothing
        if not _moves_the_odometry(n, self._data_correlation):
            return True
        self.mean = fit.mean
        self.cov = fit.cov
        self._clamp()
        return True

    def _interim(self) -> bool:
        """Before the first window closes: the open window's fit so far as the calibration in use, not committed (the
        closed window's fit replaces it, from the same prior: no fix counts twice); True when it was taken.

        A robot configured from its datasheet predicts with the prior's 10 % scale uncertainty until then, and a few
        seconds without fixes (an outlier burst) grow its position's uncertainty by a tenth of the distance driven,
        while the fixes of the window so far already know the scales far better.
        """
        # on_fix calls it only once the window has travelled, so it has steps
        steps = self._steps_t
        fit = self._solve(
            self._t0,
            np.array(steps),
            np.array(self._steps_dt),
            np.array(self._steps_u),
            self._measured_by(steps[-1]),
        )
        # the same rule as a closed window's: a correlation judged on the window so far (no windows to smooth over)
        if fit is None or not _moves_the_odometry(fit.fixes, fit.data_correlation):
            return False
        self.current = self._snapshot(np.clip(fit.mean, *_bounds(self.limits)), fit.cov)
        return True

    def _clamp(self) -> None:
        """Keep the parameters within their bounds (a fit that runs away stays bounded)."""
        self.mean = np.clip(self.mean, *_bounds(self.limits))

    def _snapshot(self, mean: FloatArray | None = None, cov: FloatArray | None = None) -> Calibration:
        """The committed calibration, or an interim mean and cov with the committed judgement of the fixes."""
        m = (self.mean if mean is None else mean).tolist()
        s = np.sqrt(np.clip(np.diag(self.cov if cov is None else cov), 0.0, None)).tolist()
        sigmas = (s[0], s[1], s[2], s[3], s[4])
        return Calibration(
            m[0],
            m[1],
            m[2],
            m[3],
            m[4],
            sigmas,
            self.windows,
            self.fix_correlated_var,
            self.fix_correlation,
            self.fix_var,
        )


@dataclass(frozen=True, slots=True)
class _WindowFit:
    """A window's fit: the calibration's posterior mean and cov, the prior it started from (walked to the window's
    end), the fixes kept, their noise variance per axis, the residuals' lag-one correlation with the prior and on
    the data alone."""

    mean: FloatArray
    cov: FloatArray
    prior_cov: FloatArray
    fixes: int
    fix_var: float
    correlation: float
    data_correlation: float


def _moves_the_odometry(fixes: int, correlation: float) -> bool:
    """Whether a window's `fixes`, of lag-one `correlation`, are worth the independent ones that its fit needs to say
    anything about the odometry.

    With fewer than that for the path's nine parameters the fit would follow the fixes' shared error (a wall's echo
    bends the path as a wrong scale would).
    """
    return fixes * information(correlation) >= MIN_INDEPENDENT_FIXES


def _bounds(limits: CalibrationLimits) -> tuple[FloatArray, FloatArray]:
    """The parameters' lower and upper bounds: scales within 1 +- scale_limit, delays within [0, latency_max_s] (the
    time check within +-latency_max_s)."""
    low = np.array([1.0 - limits.scale_limit] * 3 + [0.0, -limits.latency_max_s])
    high = np.array([1.0 + limits.scale_limit] * 3 + [limits.latency_max_s, limits.latency_max_s])
    return low, high


def _data_correlation(  # noqa: PLR0917 - the fit's arrays as they are
    path: _Path,
    params: FloatArray,
    stated: FloatArray,
    timed: npt.NDArray[np.bool_],
    zs: FloatArray,
    keep: npt.NDArray[np.bool_],
) -> float:
    """The lag-one correlation of the kept fixes' residuals after one Gauss-Newton step on the data alone.

    Residuals of the fit with its prior are correlated also when the prior holds the path back from what the fixes
    say (a robot beyond the bounds); the data's own fit leaves only what the fixes share from one to the next.
    """
    residual, jac = _residuals_and_jacobian(path, params, stated, timed, zs)
    j = jac[keep].reshape(-1, N_NUISANCE + N_CAL)
    step, *_ = np.linalg.lstsq(j, residual[keep].reshape(-1), rcond=None)
    after = residual[keep] - (j @ step).reshape(-1, 2)
    sigma2 = max(float(np.mean(after[:, 0] ** 2 + after[:, 1] ** 2)) / 2.0, 1e-12)
    return lag_one_correlation(after, sigma2)


def _relative_var(var: float, span: float) -> float:
    """An error of variance `var` (m^2 or rad^2) over a motion of `span` (m or rad) as a scale's variance, at most 1."""
    return min(var / (span * span), 1.0) if span > 0.0 else 1.0


_SCALES = [N_NUISANCE + KX, N_NUISANCE + KY, N_NUISANCE + KW]


def _normal_equations(
    j: FloatArray, r: FloatArray, noise_var: float, scale_var: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """J^T W J and J^T W r for residuals r (Jacobian j) whose covariance is noise_var I plus the window's own odometry
    error: a random error of the scales, of variances scale_var, J_s V J_s^T (J_s the scales' columns).

    Taken as exact, the odometry's random error over one window became a scale error of the fit, which the filter
    then predicted with as a systematic one. W by the Woodbury identity: (s I + J_s V J_s^T)^-1 = (I - J_s (s V^-1 +
    J_s^T J_s)^-1 J_s^T) / s, with (s V^-1 + C)^-1 = (s I + V C)^-1 V (V may be 0).
    """
    m = j.T @ j
    b = j.T @ r
    cross = m[:, _SCALES]
    k = _scale_gain(m[np.ix_(_SCALES, _SCALES)], noise_var, scale_var)
    return (m - cross @ k @ cross.T) / noise_var, (b - cross @ k @ b[_SCALES]) / noise_var


def _scale_gain(c: FloatArray, noise_var: float, scale_var: FloatArray) -> FloatArray:
    """(s V^-1 + C)^-1 = (s I + V C)^-1 V for C = J_s^T J_s, s = noise_var, V = diag(scale_var) (which may be 0):
    what the window's own odometry error takes of the scales' columns (_normal_equations), and its likeliest value
    per unit of J_s^T r (_odometry_error)."""
    v = np.diag(scale_var)
    gain: FloatArray = np.linalg.solve(noise_var * np.eye(3) + v @ c, v).astype(np.float64, copy=False)
    return gain


def _odometry_error(
    jac: FloatArray, residual: FloatArray, keep: npt.NDArray[np.bool_], scale_var: FloatArray
) -> FloatArray:
    """The part of the residuals (n x 2) that the window's own odometry error explains: its likeliest scale error
    given the kept residuals (V J_s^T (s I + J_s V J_s^T)^-1 r, s their mean square per axis), through J_s."""
    js = jac[:, :, _SCALES]
    kept_js = js[keep].reshape(-1, 3)
    kept_r = residual[keep].reshape(-1)
    noise_var = max(float(kept_r @ kept_r) / len(kept_r), 1e-12)
    error = _scale_gain(kept_js.T @ kept_js, noise_var, scale_var) @ (kept_js.T @ kept_r)
    part: FloatArray = js @ error
    return part


def _measured(stated: FloatArray, timed: npt.NDArray[np.bool_], cal: FloatArray) -> FloatArray:
    """The fixes' measurement times under the calibration's delays."""
    result: FloatArray = stated - np.where(timed, cal[TAU_K], cal[TAU_U])
    return result


class _Path:
    """A window's odometry path: steps (ends, dts, raw twists) from t0, integrated under a calibration."""

    def __init__(self, t0: float, ends: FloatArray, dts: FloatArray, us: FloatArray, offset: tuple[float, float]):
        self.times = np.concatenate([[t0], ends])
        self.dts = dts
        self.us = us
        self.offset = offset
        self.step_dist = np.hypot(us[:, 0], us[:, 1]) * dts

    def integrate(self, cal: FloatArray, psi: float) -> _Integrated:
        """The path integrated with scales cal[:3] and heading drift psi (midpoint headings)."""
        vx, vy, wz = self.us[:, 0] * cal[KX], self.us[:, 1] * cal[KY], self.us[:, 2] * cal[KW]
        dth = wz * self.dts + psi * self.step_dist * cal[KX]
        th_end = np.concatenate([[0.0], np.cumsum(dth)])
        mid = th_end[:-1] + 0.5 * dth
        c, s = np.cos(mid), np.sin(mid)
        dx, dy = (vx * c - vy * s) * self.dts, (vx * s + vy * c) * self.dts
        x = np.concatenate([[0.0], np.cumsum(dx)])
        y = np.concatenate([[0.0], np.cumsum(dy)])
        return _Integrated(self, (x, y, th_end), (dx, dy), (c, s))

    def beacon(self, cal: FloatArray, psi: float, when: FloatArray) -> tuple[FloatArray, FloatArray]:
        """The beacon's position at times `when` on the path integrated with scales cal[:3] and drift psi."""
        return self.integrate(cal, psi).beacon(when)


class _Integrated:
    """One integration of a _Path: the body's position and heading at each step's end, each step's displacement,
    and the cosine and sine of each step's midpoint heading."""

    def __init__(
        self,
        path: _Path,
        ends: tuple[FloatArray, FloatArray, FloatArray],
        steps: tuple[FloatArray, FloatArray],
        mid: tuple[FloatArray, FloatArray],
    ) -> None:
        self.path = path
        self.x, self.y, self.th_end = ends
        self.dx, self.dy = steps
        self.c, self.s = mid

    def beacon(self, when: FloatArray) -> tuple[FloatArray, FloatArray]:
        """The beacon's position at times `when` (the body's, interpolated, plus the lever arm turned by the
        heading)."""
        times = self.path.times
        px = np.interp(when, times, self.x)
        py = np.interp(when, times, self.y)
        th = np.interp(when, times, self.th_end)
        ox, oy = self.path.offset
        ct, st = np.cos(th), np.sin(th)
        return px + ox * ct - oy * st, py + ox * st + oy * ct

    def derivative(
        self, when: FloatArray, d_turn: FloatArray | float, d_step: tuple[FloatArray, FloatArray] | None = None
    ) -> tuple[FloatArray, FloatArray]:
        """The beacon's derivative at times `when` in a parameter that changes each step's turn by d_turn and, at a
        fixed heading, its displacement by d_step (x, y): the chain rule through the midpoint headings, exact for the
        path as integrated."""
        # central differences cost two integrations of the path per parameter at each of the fit's iterations: they
        # were most of a replay's calibration time
        path = self.path
        turn = np.broadcast_to(np.asarray(d_turn, dtype=np.float64), self.dx.shape)
        heading = np.cumsum(turn)
        mid = heading - 0.5 * turn  # each step's midpoint heading's change
        gx, gy = -self.dy * mid, self.dx * mid  # a step turned by a small angle moves across itself
        if d_step is not None:
            gx, gy = gx + d_step[0], gy + d_step[1]
        times = path.times
        px = np.interp(when, times, np.concatenate([[0.0], np.cumsum(gx)]))
        py = np.interp(when, times, np.concatenate([[0.0], np.cumsum(gy)]))
        dth = np.interp(when, times, np.concatenate([[0.0], heading]))
        th = np.interp(when, times, self.th_end)
        ox, oy = path.offset
        ct, st = np.cos(th), np.sin(th)
        return px - (ox * st + oy * ct) * dth, py + (ox * ct - oy * st) * dth


def _place(phi: float, tx: float, ty: float, bx: FloatArray, by: FloatArray) -> FloatArray:
    """Beacon positions (bx, by) on the window's path placed in the world: turned by phi, moved by (tx, ty)."""
    c, s = math.cos(phi), math.sin(phi)
    return np.stack([tx + c * bx - s * by, ty + s * bx + c * by], axis=1)


def _residuals_and_jacobian(
    path: _Path, params: FloatArray, stated: FloatArray, timed: npt.NDArray[np.bool_], zs: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Residuals z - f (n x 2) and the Jacobian of f (n x 2 x parameters), all from one integration of the path:
    exact for the placement, the drift and the scales (_Integrated.derivative), central differences in time for the
    delays (the path is piecewise linear in time)."""
    phi, tx, ty, psi = (float(v) for v in params[:N_NUISANCE])
    cal = params[N_NUISANCE:]
    integrated = path.integrate(cal, psi)
    when = _measured(stated, timed, cal)
    bx, by = integrated.beacon(when)
    f0 = _place(phi, tx, ty, bx, by)
    c, s = math.cos(phi), math.sin(phi)
    n = len(stated)
    jac = np.zeros((n, 2, N_NUISANCE + N_CAL))
    jac[:, 0, 1] = 1.0
    jac[:, 1, 2] = 1.0
    jac[:, 0, 0] = -s * bx - c * by  # d R(phi) b / d phi = R(phi + pi/2) b
    jac[:, 1, 0] = c * bx - s * by
    path_u, dts = path.us, path.dts
    travel = path.step_dist  # the raw odometry's metres per step: the drift turns each step by psi kx travel
    rvx, rvy = path_u[:, 0] * dts, path_u[:, 1] * dts  # the raw odometry's displacement per step, body frame
    cm, sm = integrated.c, integrated.s
    columns = (
        (3, integrated.derivative(when, travel * float(cal[KX]))),
        (N_NUISANCE + KX, integrated.derivative(when, travel * psi, (rvx * cm, rvx * sm))),
        (N_NUISANCE + KY, integrated.derivative(when, 0.0, (-rvy * sm, rvy * cm))),
        (N_NUISANCE + KW, integrated.derivative(when, path_u[:, 2] * dts)),
    )
    for k, (gx, gy) in columns:
        jac[:, 0, k] = c * gx - s * gy
        jac[:, 1, k] = s * gx + c * gy
    for kind, k in ((False, N_NUISANCE + TAU_U), (True, N_NUISANCE + TAU_K)):
        if not np.any(timed == kind):
            continue  # no fix of that kind in the window: its delay is not in the data
        h = 1e-3
        shift = np.where(timed == kind, h, 0.0)
        ux, uy = integrated.beacon(when - shift)  # tau + h: measured earlier
        dx, dy = integrated.beacon(when + shift)
        jac[:, :, k] = (_place(phi, tx, ty, ux, uy) - _place(phi, tx, ty, dx, dy)) / (2.0 * h)
    return zs - f0, jac


__all__ = ["TAU_K", "Calibration", "CalibrationLimits", "Calibrator"]
