"""`robotd tune`: the filter's noise parameters and odometry calibration fitted to recorded logs, without truth.

Theory of operation: a filter whose noise parameters are right predicts each fix with the right uncertainty, so its
innovations nu, with their predicted covariance S, have the largest likelihood: the fit minimises the negative log
likelihood of the innovations, sum over fixes of (ln det S + NIS) / 2, with robotd's own Estimator replaying each
log. A fix beyond the gate counts as if at the gate (an outlier must not decide the noise). The parameters are
searched one at a time by factors in log space (coordinate descent), within bounds no robot leaves, for a few
sweeps; a change is kept only when it lowers the total. The odometry scales are those the online calibration ends
with on each log, averaged by their precision, and the delay of fixes without a measurement time likewise. The
filter's online process noise scale is off while fitting (the fit is what it learns, done over whole logs); the
fitted noise is the prior the daemon's scale starts from.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

from robotd.config.model import EkfConfig, RobotdConfig
from robotd.estimation.estimator import Estimator
from robotd.estimation.modes import Verdict
from robotd.logs.sensorlog import IpsFix, IpsLost, SensorLog, TwistSample, Wheels
from robotd.offline.replay import robot_from_log

# (name, lower bound, upper bound): the noise parameters fitted, in the configuration's units
PARAMETERS = (
    ("ips_sigma_m", 0.005, 1.0),
    ("odom_along_sigma_m", 0.001, 0.5),
    ("odom_across_sigma_m", 0.001, 0.5),
    ("slip_heading_sigma_rad", 0.001, 0.5),
    ("turn_heading_sigma_rad", 0.001, 0.5),
)
FACTORS = (0.5, 0.75, 1.33, 2.0)
SWEEPS = 2


@dataclass(frozen=True, slots=True)
class LogFit:
    """One configuration's score on one log: the innovations' negative log likelihood, per fix, and the NIS mean."""

    nll: float
    fixes: int
    nis_mean: float


@dataclass(frozen=True, slots=True)
class TuneResult:
    """What tuning found: the fitted configuration, its score and the starting one's, the calibration, the steps."""

    ekf: EkfConfig
    latency_s: float | None  # learnt delay of fixes without a measurement time (None: every fix had its time)
    before: list[LogFit]
    after: list[LogFit]
    changes: list[str]


def score(log: SensorLog, config: RobotdConfig, ekf_config: EkfConfig) -> tuple[LogFit, Estimator]:
    """Replay one log through robotd's filter with ekf_config; the innovations' fit, and the filter at the end."""
    geometry, offset, cpr, _ = robot_from_log(log, config)
    # the fit sets the odometry noise itself: the filter's own learnt scale on it would answer for the same thing
    ekf_config = dataclasses.replace(ekf_config, adaptive_process_noise=False)
    estimator = Estimator(ekf_config, geometry, offset, cpr, default_latency_s=config.marvelmind.default_latency_s)
    nll = nis_sum = 0.0
    count = 0
    for event in log.events:
        kind = type(event)
        if kind is Wheels:
            estimator.on_wheels(event.t, event.ticks)  # type: ignore[union-attr]
        elif kind is TwistSample:
            estimator.on_twist(event.t, event.vx, event.vy, event.wz)  # type: ignore[union-attr]
        elif kind is IpsFix:
            d = estimator.on_fix(event.t, event.x, event.y, event.t_meas)  # type: ignore[union-attr]
            if d is None or d.verdict not in (Verdict.ACCEPTED, Verdict.GATED, Verdict.UNCONFIRMED):
                continue
            s_xx, s_xy, s_yy = d.s
            det = s_xx * s_yy - s_xy * s_xy
            if det <= 0.0 or not math.isfinite(d.nis):
                continue
            nis = min(d.nis, d.gate)
            nll += 0.5 * (math.log(det) + nis)
            nis_sum += nis
            count += 1
        elif kind is IpsLost:
            estimator.on_fix_lost(event.t)
    fit = LogFit(nll / count if count else math.inf, count, nis_sum / count if count else math.nan)
    return fit, estimator


def _total(fits: Sequence[LogFit]) -> float:
    return sum(f.nll * f.fixes for f in fits)


def tune(logs: Sequence[SensorLog], config: RobotdConfig) -> TuneResult:
    """Fit the noise parameters and the odometry calibration to the logs (see the module docstring)."""
    start = config.ekf
    before = [score(log, config, start)[0] for log in logs]
    best, best_total = start, _total(before)
    changes: list[str] = []
    for _ in range(SWEEPS):
        for name, low, high in PARAMETERS:
            value = getattr(best, name)
            for factor in FACTORS:
                trial_value = min(max(value * factor, low), high)
                if trial_value == value:
                    continue
                trial = dataclasses.replace(best, **{name: trial_value})
                total = _total([score(log, config, trial)[0] for log in logs])
                if total < best_total - 1e-6 * abs(best_total):
                    best, best_total = trial, total
                    value = trial_value
    for name, _, _ in PARAMETERS:
        old, new = getattr(start, name), getattr(best, name)
        if not math.isclose(old, new):
            changes.append(f"ekf.{name}: {old:.4g} -> {new:.4g}")
    # the calibration each log ends with, weighted by its precision
    weights = [0.0] * 4
    sums = [0.0] * 4
    after: list[LogFit] = []
    untimed = False
    for log in logs:
        fit, estimator = score(log, config, best)
        after.append(fit)
        c = estimator.calibration
        untimed = untimed or estimator.counters["untimed_fixes"] > 0
        for k, (value, sigma) in enumerate(zip((c.kx, c.ky, c.kw, c.latency_s), c.sigmas[:4], strict=True)):
            w = 1.0 / max(sigma, 1e-4) ** 2
            weights[k] += w
            sums[k] += w * value
    scales = tuple(round(sums[k] / weights[k], 4) for k in range(3))
    if best.calibrate and scales != tuple(start.odometry_scale):
        changes.append(f"ekf.odometry_scale: {list(start.odometry_scale)} -> {list(scales)}")
        best = dataclasses.replace(best, odometry_scale=(scales[0], scales[1], scales[2]))
    latency = round(sums[3] / weights[3], 4) if untimed else None
    if latency is not None:
        changes.append(f"marvelmind.default_latency_s: {config.marvelmind.default_latency_s:.4g} -> {latency:.4g}")
    return TuneResult(best, latency, before, after, changes)


def yaml_snippet(result: TuneResult) -> str:
    """The configuration lines tuning changed, as YAML to paste into the configuration."""
    e = result.ekf
    lines = [
        "# robotd tune: noise fitted by the innovations' likelihood, odometry scales by online calibration",
        "ekf:",
    ]
    lines += [f"  {name}: {getattr(e, name):.4g}" for name, _, _ in PARAMETERS]
    lines.append(f"  odometry_scale: [{e.odometry_scale[0]:.4g}, {e.odometry_scale[1]:.4g}, {e.odometry_scale[2]:.4g}]")
    if result.latency_s is not None:
        lines += ["marvelmind:", f"  default_latency_s: {result.latency_s:.4g}"]
    return "\n".join(lines) + "\n"


__all__ = ["PARAMETERS", "LogFit", "TuneResult", "score", "tune", "yaml_snippet"]
