"""Replay a sensor log through odometry alone, the paper's filter, a gated EKF and robotd's filter; score them against
truth.

Every method sees the same events in arrival order; an estimate is taken at every odometry input (wheel sample or
twist; at every fix in a log without inputs), from the events that arrived until then (causal). Odometry alone is
given the true initial pose (its heading fitted to the first metre of truth when truth has none): the most favourable
start, so that it is a fair baseline. The filters start from the configuration. The gated EKF (`gated_preset`) is the
textbook filter a practitioner would write: the paper's, with a chi-square gate and fixes fused at their measurement
time. The baselines exist only to be scored: a log without truth runs robotd's filter alone (their tracks stay empty).
robotd's filter may instead start from what a run before learnt (the daemon's calibration file), as the daemon does
after a restart; what it learnt by the end is written beside the estimates in that file's format.
"""

from __future__ import annotations

import contextlib
import dataclasses
import gc
import json
import math
from array import array
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import numpy.typing as npt

from robotd import kinematics
from robotd.config.model import RobotdConfig, gated_preset, paper_preset
from robotd.daemon import calibration_store
from robotd.estimation import ekf
from robotd.estimation.calibration import Calibration
from robotd.estimation.ekf import wrap_angle
from robotd.estimation.estimator import Diagnostics, Estimator, LearntNoise
from robotd.estimation.heading import fit_rotation
from robotd.logs.sensorlog import IpsFix, IpsLost, SensorLog, Truth, TwistSample, Wheels
from robotd.offline.consistency import Consistency, consistency
from robotd.offline.estimates import write_estimates
from robotd.offline.metrics import ErrorStats, Trajectory, fixes_trajectory, score

FloatArray = npt.NDArray[np.float64]
METHODS = ("odometry", "ips", "paper_ekf", "gated_ekf", "ekf")
# The baselines robotd's filter must beat (issue 14): RMSE 10 % below the best of them, a maximum no larger.
BASELINES = ("ips", "paper_ekf", "gated_ekf")


@dataclass(slots=True)
class _Estimates:
    """A method's estimates as they are taken: columns of doubles, and the covariances (P's upper triangle, six
    numbers an estimate) of the filters. Doubles, not Python floats and tuples: an hour's replay with truth holds some
    360 000 estimates of four methods, which took 350 MB more as objects."""

    t: array[float] = field(default_factory=lambda: array("d"))
    x: array[float] = field(default_factory=lambda: array("d"))
    y: array[float] = field(default_factory=lambda: array("d"))
    theta: array[float] = field(default_factory=lambda: array("d"))
    cov: array[float] = field(default_factory=lambda: array("d"))

    def append(self, t: float, estimate: tuple[float, float, float, ekf.Cov | None]) -> None:
        """Add the estimate (x, y, theta, P or None) at t; one no later than the previous is left out (a clock's
        correction that stepped back: a track runs forward)."""
        if self.t and t <= self.t[-1]:
            return
        x, y, theta, p = estimate
        self.t.append(t)
        self.x.append(x)
        self.y.append(y)
        self.theta.append(theta)
        if p is not None:
            self.cov.extend(p)

    def trajectory(self) -> Trajectory:
        """The poses as a Trajectory."""
        return Trajectory.of(self.t, self.x, self.y, self.theta)

    def covariances(self) -> FloatArray:
        """The covariances, one row (P's upper triangle) an estimate (copied)."""
        return np.array(self.cov, dtype=np.float64).reshape(-1, 6)


@dataclass(slots=True)
class ReplayResult:
    """What a replay produced: every method's estimates and score, robotd's covariances, counters and problems.

    Without truth in the log, `paper`, `gated` and `odometry` are empty and `metrics` is None.
    """

    ekf: Trajectory
    ekf_cov: FloatArray  # P's upper triangle, one row per estimate of robotd's filter
    paper: Trajectory
    gated: Trajectory
    odometry: Trajectory
    fixes: list[tuple[float, float, float]]
    metrics: dict[str, ErrorStats | None] | None
    consistency: dict[str, Consistency]  # robotd's filter always (NIS); the paper's too with truth
    calibration: Calibration  # robotd's filter's at the end of the log
    noise: LearntNoise  # robotd's filter's learnt noise at the end (the IPS noise in use, the process noise scales)
    counters: dict[str, int]
    diagnostics: list[Diagnostics]
    problems: list[str]
    unknown_types: dict[str, int]
    geometry: kinematics.Geometry
    ips_offset: tuple[float, float]
    counts_per_rev: int

    @property
    def process_noise_scale(self) -> float:
        """robotd's filter's learnt factor on the configured odometry position noise variances, at the end of the
        log."""
        return self.noise.process_noise_scale

    @property
    def heading_noise_scale(self) -> float:
        """robotd's filter's learnt factor on the configured odometry heading noise variances, at the end of the
        log."""
        return self.noise.heading_noise_scale


def robot_from_log(
    log: SensorLog, config: RobotdConfig
) -> tuple[kinematics.Geometry, tuple[float, float], int, list[str]]:
    """Geometry, beacon offset and counts per turn: the configuration, overridden by the log's meta.robot."""
    robot = log.meta.robot
    problems: list[str] = []

    def number(key: str, default: float, low: float, high: float) -> float:
        # bounds no robot leaves: a log's meta is data, and 1e300 or 0.5 counts a turn would wreck the replay
        value = robot.get(key, default)
        if isinstance(value, bool) or not isinstance(value, int | float) or not low <= value <= high:
            problems.append(
                f"meta.robot.{key}: must be a number from {low:g} to {high:g}, got {value!r}; using {default}"
            )
            return default
        return float(value)

    geometry = kinematics.Geometry(
        number("wheel_radius", config.robot.wheel_radius_m, 1e-3, 10.0),
        number("lx", config.robot.lx_m, 0.0, 100.0),  # 0: a differential-drive base
        number("ly", config.robot.ly_m, 1e-3, 100.0),
    )
    cpr = int(number("counts_per_rev", config.encoders.counts_per_rev, 1.0, 1e9))
    offset, problem = beacon_offset(log, config)
    if problem is not None:
        problems.append(f"{problem}; using {list(offset)}")
    return geometry, offset, cpr, problems


def beacon_offset(log: SensorLog, config: RobotdConfig) -> tuple[tuple[float, float], str | None]:
    """The beacon's offset from the robot's centre: the log's meta.robot.ips_offset, else the configuration's; with
    why the meta's is not used when it is unusable (None when it was fine or absent)."""
    offset = config.robot.ips_offset_m
    raw = log.meta.robot.get("ips_offset", list(offset))
    if (
        isinstance(raw, list)
        and len(raw) == 2
        and all(isinstance(v, int | float) and not isinstance(v, bool) and abs(v) <= 100.0 for v in raw)
    ):
        return (float(raw[0]), float(raw[1])), None
    return offset, f"meta.robot.ips_offset: must be a list of 2 numbers within ±100, got {raw!r}"


@contextlib.contextmanager
def _out_of_collectors_sight() -> Iterator[None]:
    """While inside, the objects made before are left out of the cyclic collector's passes (gc.freeze).

    A replay holds the log's events, and then its estimates, alive throughout: each full pass walked them all, a
    tenth of an hour's replay and of writing its estimates (refcounting still frees them after). A process that had
    frozen objects of its own (the daemon freezes what it built at start) keeps them frozen: unfreezing is all or none,
    so the replay's objects then stay out of sight too.
    """
    frozen_by_caller = gc.get_freeze_count() > 0
    gc.freeze()
    try:
        yield
    finally:
        if not frozen_by_caller:
            gc.unfreeze()


def replay(log: SensorLog, config: RobotdConfig, start: calibration_store.Saved | None = None) -> ReplayResult:
    """Run the four methods over a parsed log, event by event through the daemon's Estimator, and score them when
    the log holds truth (robotd's filter alone without); robotd's filter starts from `start` when given.

    Odometry alone is an Estimator that is never given a fix, started at the origin and placed on the true start.
    """
    with _out_of_collectors_sight():
        return _replay(log, config, start)


def _replay(log: SensorLog, config: RobotdConfig, start: calibration_store.Saved | None) -> ReplayResult:
    geometry, offset, cpr, problems = robot_from_log(log, config)
    events = log.events
    truth_samples = [(e.t, e.x, e.y, e.theta) for e in events if isinstance(e, Truth)]
    truth = Trajectory.from_samples(truth_samples) if truth_samples else None
    scored = truth is not None  # the baselines exist only to be scored
    robotd = Estimator(
        config.ekf,
        geometry,
        offset,
        cpr,
        default_latency_s=config.marvelmind.default_latency_s,
        calibration=None if start is None else start.calibration,
        noise=None if start is None else start.noise,
    )
    paper = gated = odometry = None
    if scored:
        paper = Estimator(paper_preset(config.ekf), geometry, offset, cpr)
        latency = config.marvelmind.default_latency_s
        gated = Estimator(gated_preset(config.ekf), geometry, offset, cpr, default_latency_s=latency)
        odo_config = dataclasses.replace(config.ekf, initial_pose=(0.0, 0.0, 0.0))  # local frame, placed on truth later
        odometry = Estimator(odo_config, geometry, offset, cpr)
    filters = tuple(est for est in (robotd, paper, gated, odometry) if est is not None)
    taken = (_Estimates(), _Estimates(), _Estimates(), _Estimates())  # robotd's, the paper's, the gated, odometry's
    baselines = [(estimates, est) for estimates, est in ((taken[1], paper), (taken[2], gated)) if est is not None]
    outputs = [(taken[0], robotd), *baselines]
    # an output at every input (wheel samples, twists; fixes only in a log without inputs)
    inputs = any(type(e) is Wheels or type(e) is TwistSample for e in events)
    fixes: list[tuple[float, float, float]] = []
    diagnostics: list[Diagnostics] = []
    for event in events:
        if isinstance(event, Wheels):
            for est in filters:
                est.on_wheels(event.t, event.ticks)
        elif isinstance(event, TwistSample):
            for est in filters:
                est.on_twist(event.t, event.vx, event.vy, event.wz)
        elif isinstance(event, IpsFix):
            diagnostic = robotd.on_fix(event.t, event.x, event.y, event.t_meas)
            robotd.settle()  # what it learns from the fix, at once: the daemon's later outputs are the same
            if diagnostic is not None:
                diagnostics.append(diagnostic)
            for _, baseline in baselines:
                baseline.on_fix(event.t, event.x, event.y, event.t_meas)
                baseline.settle()
            if math.isfinite(event.x) and math.isfinite(event.y) and math.isfinite(event.stated_t):
                fixes.append((event.stated_t, event.x, event.y))
            if inputs:
                continue
        else:
            if isinstance(event, IpsLost):
                robotd.on_fix_lost(event.t)
                for _, baseline in baselines:
                    baseline.on_fix_lost(event.t)
            continue
        t = event.t
        for estimates, est in outputs:
            position = est.position(t)
            if position is not None:
                estimates.append(t + est.clock_offset_s, position)
        if odometry is not None:  # never placed by a fix: the initial pose carried
            pose = odometry.pose(t)
            taken[3].append(t, (pose.x, pose.y, pose.theta, None))
    _place_odometry(taken[3], truth)
    ours, papers, gateds, odometry_alone = (estimates.trajectory() for estimates in taken)
    metrics = None
    ekf_cov = taken[0].covariances()
    honesty = {"ekf": consistency(truth, ours, ekf_cov, diagnostics)}
    if truth is not None:
        honesty["paper_ekf"] = consistency(truth, papers, taken[1].covariances(), ())
        honesty["gated_ekf"] = consistency(truth, gateds, taken[2].covariances(), ())
        metrics = {
            "odometry": score(truth, odometry_alone),
            "ips": score(truth, fixes_trajectory(fixes, offset, truth)),
            "paper_ekf": score(truth, papers),
            "gated_ekf": score(truth, gateds),
            "ekf": score(truth, ours),
        }
    return ReplayResult(
        ekf=ours,
        ekf_cov=ekf_cov,
        paper=papers,
        gated=gateds,
        odometry=odometry_alone,
        fixes=fixes,
        metrics=metrics,
        consistency=honesty,
        calibration=robotd.calibration,
        noise=robotd.learnt_noise,
        counters=dict(robotd.counters),
        diagnostics=diagnostics,
        problems=list(log.problems) + problems,
        unknown_types=dict(log.unknown_types),
        geometry=geometry,
        ips_offset=offset,
        counts_per_rev=cpr,
    )


def _place_odometry(odometry: _Estimates, truth: Trajectory | None) -> None:
    """Put the odometry track, computed from (0, 0, 0), on the true initial pose (evaluation only: the filters never
    see truth); without a true heading, turned by the rotation that best lays its first metre onto the truth."""
    if not odometry.t or truth is None:
        return
    x0, y0, th0, _ = truth.at(np.array(odometry.t[:1]))
    theta0 = float(th0[0])
    if not math.isfinite(theta0):
        travelled = 0.0
        end = 1
        while end < len(odometry.t) and travelled < 1.0:
            travelled += math.hypot(odometry.x[end] - odometry.x[end - 1], odometry.y[end] - odometry.y[end - 1])
            end += 1
        tx, ty, _, _ = truth.at(np.array(odometry.t[:end]))
        theta0 = fit_rotation(odometry.x[:end].tolist(), odometry.y[:end].tolist(), tx.tolist(), ty.tolist())[0]
    c, s = math.cos(theta0), math.sin(theta0)
    for i, (x, y) in enumerate(zip(odometry.x, odometry.y, strict=True)):
        odometry.x[i], odometry.y[i] = float(x0[0]) + x * c - y * s, float(y0[0]) + x * s + y * c
        odometry.theta[i] = wrap_angle(odometry.theta[i] + theta0)


def write_outputs(result: ReplayResult, out_dir: Path) -> list[Path]:
    """Write estimates.jsonl (robotd's filter), calibration.json (what it learnt, in the daemon's calibration file
    format) and, with truth, metrics.json; returns the paths written."""
    out_dir.mkdir(parents=True, exist_ok=True)
    written = [out_dir / "estimates.jsonl"]
    e = result.ekf
    with open(written[0], "wb") as stream, _out_of_collectors_sight():
        write_estimates(stream, np.column_stack([e.t, e.x, e.y, e.theta]), result.ekf_cov)
    written.append(out_dir / "calibration.json")
    calibration_store.save(written[-1], result.calibration, result.noise)
    if result.metrics is not None:
        metrics: dict[str, dict[str, float | int | None] | None] = {
            name: (dict(stats.as_dict()) if stats is not None else None) for name, stats in result.metrics.items()
        }
        for name, honesty in result.consistency.items():
            entry = metrics.get(name)
            if entry is not None:
                entry.update(honesty.as_dict())
        ekf_entry = metrics.get("ekf")
        if ekf_entry is not None:
            ekf_entry.update({f"calibration_{key}": value for key, value in result.calibration.as_dict().items()})
            ekf_entry["process_noise_scale"] = round(result.process_noise_scale, 5)
            ekf_entry["heading_noise_scale"] = round(result.heading_noise_scale, 5)
        written.append(out_dir / "metrics.json")
        written[-1].write_text(json.dumps(metrics, indent=2) + "\n", encoding="utf-8")
    return written


def format_table(result: ReplayResult) -> str:
    """The short table printed by `robotd replay`."""
    lines = []
    if result.metrics is not None:
        lines.append(
            f"{'method':10s} {'rmse_m':>8s} {'max_m':>8s} {'final_m':>8s} {'median_m':>9s} {'heading_deg':>11s}"
        )
        for name in METHODS:
            stats = result.metrics.get(name)
            if stats is None:
                lines.append(f"{name:10s} {'-':>8s}")
                continue
            heading = f"{stats.heading_rmse_deg:11.2f}" if stats.heading_rmse_deg is not None else f"{'-':>11s}"
            figures = f"{stats.rmse_m:8.3f} {stats.max_m:8.3f} {stats.final_m:8.3f} {stats.median_m:9.3f}"
            lines.append(f"{name:10s} {figures} {heading}")
    for name, honesty in result.consistency.items():
        lines.append(_consistency_line(name, honesty))
    lines.append(_calibration_line(result.calibration, result.counters))
    lines.append(
        f"process noise (learnt): x{result.process_noise_scale:.3f} the configured odometry position noise variances,"
        f" x{result.heading_noise_scale:.3f} the heading's"
    )
    c = result.counters
    lines.append(
        f"fixes {c['fixes']}: accepted {c['fixes_accepted']}, rejected {c['fixes_rejected']}, "
        f"recoveries {c['recoveries']}, heading re-aligned {c['heading_realigned']}, lost {c['fixes_lost']}, "
        f"late {c['late_fixes']}, too old {c['fixes_too_old']}, "
        f"dropped {c['dropped_non_finite'] + c['dropped_out_of_order']}"
    )
    if c["odometry_pauses"]:
        lines.append(
            f"odometry paused {c['odometry_pauses']} time(s) while the robot moved (the motion in each gap bridged as "
            f"a guess); the heading was lost after {c['heading_lost']} of them"
        )
    if result.unknown_types:
        lines.append("unknown event types: " + ", ".join(f"{k} x{v}" for k, v in sorted(result.unknown_types.items())))
    return "\n".join(lines)


def _calibration_line(calibration: Calibration, counters: dict[str, int]) -> str:
    """The odometry scales and fix delays robotd's filter ended with, each with its standard deviation."""
    c, s = calibration, calibration.as_dict()
    delay = (
        f"latency of fixes without a measurement time {c.latency_s * 1000:.0f} +- {c.sigmas[3] * 1000:.0f} ms "
        f"({counters['untimed_fixes']} such fixes)"
        if counters["untimed_fixes"]
        else f"stated measurement times off by {c.time_error_s * 1000:+.0f} +- {c.sigmas[4] * 1000:.0f} ms"
    )
    return (
        f"calibration ({c.windows} windows): wheel radius x{c.wheel_radius_scale:.4f} "
        f"+- {s['wheel_radius_scale_sigma']:.4f}, "
        f"lateral x{c.lateral_scale:.4f} +- {s['lateral_scale_sigma']:.4f}, "
        f"rotation x{c.rotation_scale:.4f} +- {s['rotation_scale_sigma']:.4f}; {delay}"
    )


def _consistency_line(name: str, honesty: Consistency) -> str:
    """One line on whether a filter's covariance is honest: NEES against truth, NIS of its accepted fixes."""

    def figure(value: float | None, digits: int) -> str:
        return "-" if value is None else f"{value:.{digits}f}"

    parts = [f"{name:10s} consistency:"]
    if honesty.nees_mean is not None:
        parts.append(
            f"NEES mean {figure(honesty.nees_mean, 2)} (2 when honest), truth inside the 95 % ellipse "
            f"{figure(honesty.inside_95, 3)} (0.95),"
        )
    parts.append(
        f"NIS mean {figure(honesty.nis_mean, 2)}, within 95 % {figure(honesty.nis_within_95, 3)} "
        f"({honesty.fixes_accepted} accepted fixes)"
    )
    return " ".join(parts)


__all__ = [
    "BASELINES",
    "METHODS",
    "ReplayResult",
    "format_table",
    "replay",
    "robot_from_log",
    "write_outputs",
]
