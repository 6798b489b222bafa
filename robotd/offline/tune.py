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

On request (`robotd tune --lever-arm`), the beacon's lever arm (robot.ips_offset_m) is fitted the same way, before
the noise and again after it. Only on request: on the libRSF robot's real UWB fixes it found a lever arm of 13 cm
that motion-capture truth does not show (truth given as fixes: none found) and that made the replay's error larger,
a bias of the radio's that turns with the robot as a lever arm would (presumably the body shadowing some anchors).
A lever arm measured wrong, or not declared, puts a bias on every fix that turns with the robot, which the noise
would otherwise absorb. Only rotation shows it (driving straight, a lever arm is a constant shift that the position
takes up), so it is fitted only on the logs whose robot turned by a quarter turn or more (MIN_TURN_RAD, the filter's
heading at each fix): without turns a made-up lever arm gives the filter's heading a handle on the fixes, which fits
their noise (a square driven without turning took a 16 cm lever arm that was not there). It is searched by steps in
each axis, halved down to OFFSET_RESOLUTION_M, and kept only when it passes a likelihood-ratio test against the one
the logs declare (2 dof at 95 %: the total negative log likelihood lower by SIGNIFICANT_NLL, each log's fixes
counted for what their innovations' correlation leaves them worth) and differs from it by OFFSET_MIN_CHANGE_M or
more (a smaller change is within what one log's fit can tell). The fitted lever arm is one for every log (the same
robot's), in place of the one each log declares.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from robotd.config.model import EkfConfig, RobotdConfig
from robotd.estimation.ar1 import information, lag_one_correlation
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
OFFSET_FIRST_STEP_M = 0.08  # the lever arm's first step per axis, halved down to OFFSET_RESOLUTION_M
OFFSET_RESOLUTION_M = 0.005
OFFSET_LIMIT_M = 1.0  # a beacon further than this from the centre is not on the robot
SIGNIFICANT_NLL = 3.0  # half the chi-square 95 % point for 2 dof (5.99): the lever arm's likelihood-ratio test
# a lever arm moves a fix by its length times the turn between fixes: a robot that turned less than a quarter turn
# shows its lever arm only through the filter's heading, whose errors a wrong lever arm can fit as well
MIN_TURN_RAD = math.pi / 2.0
# what one log's fit can tell: on the virtual robot's turning logs it found a lever arm 1-2.5 cm from the truth, and a
# declared lever arm 1 cm off costs a replay a third more RMSE: a smaller change would be the fit's own error
OFFSET_MIN_CHANGE_M = 0.02


@dataclass(frozen=True, slots=True)
class LogFit:
    """One configuration's score on one log: the innovations' negative log likelihood, per fix, and the NIS mean."""

    nll: float
    fixes: int
    nis_mean: float
    turned_rad: float = 0.0  # the range of the filter's heading over the fixes (max - min, unwrapped; when measured)
    correlation: float = 0.0  # lag-one correlation of the accepted fixes' innovations, each axis scaled by its S


@dataclass(frozen=True, slots=True)
class TuneResult:
    """What tuning found: the fitted configuration, its score and the starting one's, the calibration, the steps."""

    ekf: EkfConfig
    latency_s: float | None  # learnt delay of fixes without a measurement time (None: every fix had its time)
    ips_offset: tuple[float, float] | None  # the fitted lever arm (None: the declared one stays)
    before: list[LogFit]
    after: list[LogFit]
    changes: list[str]
    notes: list[str] = dataclasses.field(default_factory=list)  # what was not fitted, and why


def score(
    log: SensorLog,
    config: RobotdConfig,
    ekf_config: EkfConfig,
    offset: tuple[float, float] | None = None,
    *,
    measure_turn: bool = False,
) -> tuple[LogFit, Estimator]:
    """Replay one log through robotd's filter with ekf_config (and the beacon at `offset`, else where the log or the
    configuration says); the innovations' fit (with `measure_turn`, how far the robot turned), and the filter at the
    end."""
    geometry, declared, cpr, _ = robot_from_log(log, config)
    offset = declared if offset is None else offset
    # the fit sets the odometry noise itself: the filter's own learnt scale on it would answer for the same thing
    ekf_config = dataclasses.replace(ekf_config, adaptive_process_noise=False)
    estimator = Estimator(ekf_config, geometry, offset, cpr, default_latency_s=config.marvelmind.default_latency_s)
    nll = nis_sum = 0.0
    count = 0
    heading = low = high = 0.0  # unwrapped, at the fixes
    whitened: list[tuple[float, float]] = []
    for event in log.events:
        kind = type(event)
        if kind is Wheels:
            estimator.on_wheels(event.t, event.ticks)  # type: ignore[union-attr]
        elif kind is TwistSample:
            estimator.on_twist(event.t, event.vx, event.vy, event.wz)  # type: ignore[union-attr]
        elif kind is IpsFix:
            d = estimator.on_fix(event.t, event.x, event.y, event.t_meas)  # type: ignore[union-attr]
            estimator.settle()
            if d is None or d.verdict not in (Verdict.ACCEPTED, Verdict.GATED, Verdict.UNCONFIRMED):
                continue
            s_xx, s_xy, s_yy = d.s
            det = s_xx * s_yy - s_xy * s_xy
            if det <= 0.0 or not math.isfinite(d.nis):
                continue
            nis = min(d.nis, d.gate)
            nll += 0.5 * (math.log(det) + nis)
            if measure_turn:  # a pose per fix: a tenth more time per replay, needed once per log
                heading += math.remainder(estimator.pose().theta - heading, math.tau)
                low, high = min(low, heading), max(high, heading)
            if d.verdict is Verdict.ACCEPTED:
                whitened.append((d.nu[0] / math.sqrt(s_xx), d.nu[1] / math.sqrt(s_yy)))
            nis_sum += nis
            count += 1
        elif kind is IpsLost:
            estimator.on_fix_lost(event.t)
    rho = lag_one_correlation(np.array(whitened), 1.0) if whitened else 0.0
    fit = LogFit(nll / count if count else math.inf, count, nis_sum / count if count else math.nan, high - low, rho)
    return fit, estimator


def _total(fits: Sequence[LogFit]) -> float:
    return sum(f.nll * f.fixes for f in fits)


def tune(logs: Sequence[SensorLog], config: RobotdConfig, *, lever_arm: bool = False) -> TuneResult:
    """Fit the noise parameters and the odometry calibration to the logs, and with `lever_arm` the beacon's lever arm
    (see the module docstring)."""
    start = config.ekf
    before = [score(log, config, start, measure_turn=lever_arm)[0] for log in logs]
    # None: each log's own lever arm (its meta's, else the configuration's); a fitted one replaces them all
    offset: tuple[float, float] | None = None
    declared = robot_from_log(logs[0], config)[1]
    turning = [log for log, fit in zip(logs, before, strict=True) if fit.turned_rad >= MIN_TURN_RAD]
    notes: list[str] = []
    if lever_arm and turning:
        offset = _fit_offset(turning, config, start, declared, declared)
    elif lever_arm:
        turned = max((math.degrees(fit.turned_rad) for fit in before), default=0.0)
        notes.append(
            f"robot.ips_offset_m not fitted: the robot turned by {turned:.0f} deg at most, and only turns show the"
            f" beacon's lever arm (a log with a quarter turn or more would)"
        )
    best = start
    best_total = _total(before) if offset is None else _total([score(log, config, start, offset)[0] for log in logs])
    changes: list[str] = []
    for _ in range(SWEEPS):
        for name, low, high in PARAMETERS:
            value = getattr(best, name)
            for factor in FACTORS:
                trial_value = min(max(value * factor, low), high)
                if trial_value == value:
                    continue
                trial = dataclasses.replace(best, **{name: trial_value})
                total = _total([score(log, config, trial, offset)[0] for log in logs])
                if total < best_total - 1e-6 * abs(best_total):
                    best, best_total = trial, total
                    value = trial_value
    if lever_arm and turning:  # again, with the noise it let the fit find
        offset = _fit_offset(turning, config, best, offset or declared, declared)
    if offset is not None:
        changes.append(
            f"robot.ips_offset_m: [{declared[0]:.4g}, {declared[1]:.4g}] -> [{offset[0]:.4g}, {offset[1]:.4g}]"
            " (the fixes' bias turns with the robot: the beacon's lever arm)"
        )
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
        fit, estimator = score(log, config, best, offset)
        after.append(fit)
        c = estimator.calibration
        untimed = untimed or estimator.counters["untimed_fixes"] > 0
        for k, (value, sigma) in enumerate(zip((c.kx, c.ky, c.kw, c.latency_s), c.sigmas[:4], strict=True)):
            w = 1.0 / max(sigma, 1e-4) ** 2
            weights[k] += w
            sums[k] += w * value
    scales = tuple(round(sums[k] / weights[k], 4) for k in range(3))
    if best.calibrate and scales != tuple(start.odometry_scale):
        changes.append(f"ekf.odometry_scale: {_scales(start.odometry_scale)} -> {_scales(scales)}")
        best = dataclasses.replace(best, odometry_scale=(scales[0], scales[1], scales[2]))
    latency = round(sums[3] / weights[3], 4) if untimed else None
    if latency is not None:
        changes.append(f"marvelmind.default_latency_s: {config.marvelmind.default_latency_s:.4g} -> {latency:.4g}")
    return TuneResult(best, latency, offset, before, after, changes, notes)


def _fit_offset(
    logs: Sequence[SensorLog],
    config: RobotdConfig,
    ekf_config: EkfConfig,
    start: tuple[float, float],
    declared: tuple[float, float],
) -> tuple[float, float] | None:
    """The lever arm that makes the logs' fixes most likely, searched from `start` by halving steps per axis; None
    (the declared one stays) unless it passes the tests against `declared` (module docstring)."""
    scored: dict[tuple[float, float], list[LogFit]] = {}

    def fits(offset: tuple[float, float]) -> list[LogFit]:
        if offset not in scored:  # the test below needs the start's and the best's again
            scored[offset] = [score(log, config, ekf_config, offset)[0] for log in logs]
        return scored[offset]

    best, best_total = start, _total(fits(start))
    step = OFFSET_FIRST_STEP_M
    while step >= OFFSET_RESOLUTION_M:
        moved = False
        for dx, dy in ((step, 0.0), (-step, 0.0), (0.0, step), (0.0, -step)):
            trial = (round(best[0] + dx, 4), round(best[1] + dy, 4))
            if math.hypot(*trial) > OFFSET_LIMIT_M:
                continue
            trial_total = _total(fits(trial))
            if trial_total < best_total:
                best, best_total, moved = trial, trial_total, True
                break
        if not moved:
            step /= 2.0
    if math.dist(best, declared) < OFFSET_MIN_CHANGE_M:
        return None
    # the test counts each log's fixes for what they are worth: innovations that persist from fix to fix are fewer
    # independent ones (robotd.estimation.ar1), and a sum over them would overstate the evidence
    gain = sum(
        (old.nll - new.nll) * new.fixes * information(new.correlation)
        for old, new in zip(fits(declared), fits(best), strict=True)
    )
    return best if gain >= SIGNIFICANT_NLL else None


def _scales(scales: Sequence[float]) -> str:
    """Odometry scales as a YAML list, every digit tuning kept (4 decimals: 4 significant digits made 1.0002 a 1)."""
    return "[" + ", ".join(f"{v:.6g}" for v in scales) + "]"


def yaml_snippet(result: TuneResult) -> str:
    """The configuration lines tuning changed, as YAML to paste into the configuration."""
    e = result.ekf
    lines = [
        "# robotd tune: noise and lever arm by the innovations' likelihood, odometry scales by online calibration",
        "ekf:",
    ]
    lines += [f"  {name}: {getattr(e, name):.4g}" for name, _, _ in PARAMETERS]
    lines.append(f"  odometry_scale: {_scales(e.odometry_scale)}")
    if result.latency_s is not None:
        lines += ["marvelmind:", f"  default_latency_s: {result.latency_s:.4g}"]
    if result.ips_offset is not None:
        lines += ["robot:", f"  ips_offset_m: [{result.ips_offset[0]:.4g}, {result.ips_offset[1]:.4g}]"]
    return "\n".join(lines) + "\n"


__all__ = ["PARAMETERS", "LogFit", "TuneResult", "score", "tune", "yaml_snippet"]
