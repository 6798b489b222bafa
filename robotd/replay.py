"""Replay a sensor log through odometry alone, the paper's filter and robotd's filter, and score them against truth.

Every method sees the same events in arrival order; an estimate is taken every `OUTPUT_PERIOD_S` of log time (at
the first event at least that long after the previous estimate: the daemon's pose stream), from the events that
arrived until then (causal). Odometry alone is given the
true initial pose (its heading fitted to the first metre of truth when truth has none): the most favourable start,
so that it is a fair baseline. The filters start from the configuration. The baselines exist only to be scored: a
log without truth runs robotd's filter alone (their tracks stay empty).
"""

from __future__ import annotations

import bisect
import contextlib
import dataclasses
import gc
import json
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import numpy.typing as npt

from robotd import deadreckoning, ekf, kinematics
from robotd.config import RobotdConfig
from robotd.estimates import ReplayEstimator
from robotd.estimates_file import write_estimates
from robotd.estimator import Diagnostics, Estimator
from robotd.logfile import Event, IpsFix, IpsLost, SensorLog, TwistSample
from robotd.metrics import ErrorStats, TruthTrack, fit_rotation, score, score_fixes
from robotd.wheelsteps import PERIOD_SLACK_S, step_ends

OUTPUT_PERIOD_S = 0.05  # the daemon's default pose rate (pose_socket.rate_hz: 20)
METHODS = ("odometry", "ips", "paper_ekf", "ekf")


@dataclass(slots=True)
class Track:
    """A method's estimates over time; `cov` (P's upper triangle: xx, xy, xt, yy, yt, tt) is empty for odometry."""

    t: list[float] = field(default_factory=list)
    x: list[float] = field(default_factory=list)
    y: list[float] = field(default_factory=list)
    theta: list[float] = field(default_factory=list)
    cov: list[ekf.Cov] | npt.NDArray[np.float64] = field(default_factory=list)


@dataclass(slots=True)
class ReplayResult:
    """What a replay produced: robotd's estimates, every method's track and score, counters and problems.

    Without truth in the log, `paper` and `odometry` are empty and `metrics` is None.
    """

    ekf: Track
    paper: Track
    odometry: Track
    fixes: list[tuple[float, float, float]]
    metrics: dict[str, ErrorStats | None] | None
    counters: dict[str, int]
    diagnostics: list[Diagnostics]
    problems: list[str]
    unknown_types: dict[str, int]
    geometry: kinematics.Geometry
    ips_offset: tuple[float, float]
    counts_per_rev: int


@contextlib.contextmanager
def cyclic_gc_paused() -> Iterator[None]:
    """Pause Python's cyclic garbage collector for a replay (restored after, as it was).

    A replay builds a few hundred thousand long-lived objects and no reference cycles: the collector's passes over
    them would be pure cost (a fifth of the run).
    """
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


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
        number("lx", config.robot.lx_m, 1e-3, 100.0),
        number("ly", config.robot.ly_m, 1e-3, 100.0),
    )
    cpr = int(number("counts_per_rev", config.encoders.counts_per_rev, 1.0, 1e9))
    offset = config.robot.ips_offset_m
    raw = robot.get("ips_offset", list(offset))
    if (
        isinstance(raw, list)
        and len(raw) == 2
        and all(isinstance(v, int | float) and not isinstance(v, bool) and abs(v) <= 100.0 for v in raw)
    ):
        offset = (float(raw[0]), float(raw[1]))
    else:
        problems.append(
            f"meta.robot.ips_offset: must be a list of 2 numbers within ±100, got {raw!r}; using {list(offset)}"
        )
    return geometry, offset, cpr, problems


def _record_odometry(track: Track, t: float, est: Estimator) -> None:
    """Append the dead-reckoning estimate at t (an Estimator that never sees a fix: always has a pose)."""
    pose = est.pose(t)
    track.t.append(t)
    track.x.append(pose.x)
    track.y.append(pose.y)
    track.theta.append(pose.theta)


def _marked_track(est: ReplayEstimator) -> Track:
    """The outputs an estimator marked, as a Track."""
    t, x, y, theta, cov = est.marked()
    return Track(t, x, y, theta, cov)


def replay(log: SensorLog, config: RobotdConfig) -> ReplayResult:
    """Run the three methods over a parsed log and score them when it holds truth (robotd's filter alone without).

    The log is read as columns (SensorLog.columns): wheel samples reach the filters in runs between the other
    events (ReplayEstimator.on_wheel_samples), the same inputs in the same order as one on_wheels call each; a clean
    wheel column, or twists alone, is loaded at once (ReplayEstimator.load_wheels, load_twists) and the outputs are
    marked and computed together at the end (ReplayEstimator.marked). Odometry alone is computed for the whole log at
    once (robotd.deadreckoning) when its wheel times are clean and it has no twist samples, and with a third
    estimator otherwise.
    """
    geometry, offset, cpr, problems = robot_from_log(log, config)
    columns = log.columns()
    scored = len(columns.truth) > 0  # the baselines exist only to be scored: without truth, robotd's filter alone
    robotd = ReplayEstimator(config.ekf, geometry, offset, cpr)
    paper = ReplayEstimator.paper_filter(config.ekf, geometry, cpr) if scored else None
    times: list[float] = columns.wheels_t.tolist()
    others = columns.others
    after: list[int] = columns.others_after().tolist()
    is_twist = [type(e) is TwistSample for e in others]
    has_twists = any(is_twist)
    vectorised = deadreckoning.applies(columns.wheels_t) and not has_twists
    odometry: ReplayEstimator | None = None
    if scored and not vectorised:
        odo_config = dataclasses.replace(config.ekf, initial_pose=(0.0, 0.0, 0.0))  # local frame, placed on truth later
        odometry = ReplayEstimator(odo_config, geometry, offset, cpr)
    filters = tuple(est for est in (robotd, paper, odometry) if est is not None)
    # A clean input column (wheels, or twists alone) makes all its prediction steps at once (numpy), and outputs are
    # computed together; the other events are fed between runs of its samples (`events`, `events_after`).
    loaded = False
    step_period = config.ekf.predict_period_s
    input_t, events, events_after = times, others, after
    ends = step_ends(times, step_period) if not has_twists and odometry is None else []
    if ends:
        outcomes = [est.load_wheels(columns.wheels_t, columns.wheels_ticks, ends) for est in filters]
        loaded = all(outcomes)  # (the same columns: all or none)
    elif has_twists and not times:
        twists = np.array([(e.t, e.vx, e.vy, e.wz) for e in others if type(e) is TwistSample], dtype=np.float64)
        outcomes = [est.load_twists(twists[:, 0], twists[:, 1], twists[:, 2], twists[:, 3]) for est in filters]
        loaded = all(outcomes)
        if loaded:
            input_t = twists[:, 0].tolist()
            events = [e for e, twist in zip(others, is_twist, strict=True) if not twist]
            twists_before = np.cumsum(is_twist)  # (at an event that is not a twist: the twists before it)
            events_after = twists_before[~np.array(is_twist)].tolist()
    odometry_track = Track()
    odo_records: tuple[list[float], list[int]] = ([], [])  # record times and wheel samples before them
    fixes: list[tuple[float, float, float]] = []
    diagnostics: list[Diagnostics] = []

    def on_event(event: Event) -> None:
        if type(event) is IpsFix:
            diagnostic = robotd.on_fix(event.t, event.x, event.y, event.t_meas)
            if diagnostic is not None:
                diagnostics.append(diagnostic)
            if paper is not None:
                paper.on_fix(event.t, event.x, event.y, event.t_meas)
            if math.isfinite(event.x) and math.isfinite(event.y) and math.isfinite(event.t_meas):
                fixes.append((event.t_meas, event.x, event.y))
        elif type(event) is TwistSample:
            for est in filters:
                est.on_twist(event.t, event.vx, event.vy, event.wz)
        elif type(event) is IpsLost:
            robotd.on_fix_lost(event.t)
            if paper is not None:
                paper.on_fix_lost(event.t)

    if loaded:
        # outputs at the input samples that end each OUTPUT_PERIOD_S, marked in runs between the other events
        marks = ends if ends and step_period == OUTPUT_PERIOD_S else step_ends(input_t, OUTPUT_PERIOD_S)
        mark_array = np.array(marks, dtype=np.int64)
        fed = marked = 0
        for index in range(len(events) + 1):
            stop = events_after[index] if index < len(events) else len(input_t)
            if fed < stop:
                for est in filters:
                    est.on_loaded_samples(fed, stop)
                fed = stop
            upto = bisect.bisect_left(marks, stop, marked)
            if upto > marked:
                robotd.mark_samples(mark_array[marked:upto])
                if paper is not None:
                    paper.mark_samples(mark_array[marked:upto])
                if odometry is not None:
                    odometry.mark_samples(mark_array[marked:upto], unplaced=True)
                marked = upto
            if index < len(events):
                on_event(events[index])
        if odometry is not None:
            odometry_track = _marked_track(odometry)
        elif scored:  # (wheels: dead reckoning below, at the same outputs)
            odo_records[0].extend(columns.wheels_t[mark_array].tolist())
            odo_records[1].extend((mark_array + 1).tolist())
    else:
        # an output every OUTPUT_PERIOD_S of input time (wheel samples, twists; fixes only in a log without inputs)
        inputs = bool(times) or has_twists
        ticks: list[tuple[int, int, int, int]] = list(
            zip(*(column.tolist() for column in columns.wheels_ticks.T), strict=True)
        )
        last_out = -math.inf
        fed = 0

        def record(t: float, samples: int) -> None:
            robotd.mark(t)
            if paper is None:
                return
            paper.mark(t)
            if odometry is not None:
                _record_odometry(odometry_track, t, odometry)
            else:
                odo_records[0].append(t)
                odo_records[1].append(samples)

        for index in range(len(others) + 1):
            stop = after[index] if index < len(others) else len(times)
            for i in range(fed, stop):
                if times[i] - last_out >= OUTPUT_PERIOD_S - PERIOD_SLACK_S:
                    for est in filters:
                        est.on_wheel_samples(times, ticks, fed, i + 1)
                    fed = i + 1
                    record(times[i], fed)
                    last_out = times[i]
            if fed < stop:
                for est in filters:
                    est.on_wheel_samples(times, ticks, fed, stop)
                fed = stop
            if index == len(others):
                break
            event = others[index]
            on_event(event)
            output = type(event) is TwistSample or (type(event) is IpsFix and not inputs)
            if output and event.t - last_out >= OUTPUT_PERIOD_S - PERIOD_SLACK_S:
                record(event.t, fed)
                last_out = event.t
    if scored and odometry is None:
        ox, oy, oth = deadreckoning.poses_at(
            columns.wheels_t,
            columns.wheels_ticks,
            np.array(odo_records[0], dtype=np.float64),
            np.array(odo_records[1], dtype=np.int64),
            geometry,
            cpr,
            config.ekf.predict_period_s,
        )
        odometry_track = Track(odo_records[0], ox.tolist(), oy.tolist(), oth.tolist())
    tracks = (_marked_track(robotd), _marked_track(paper) if paper is not None else Track(), odometry_track)
    metrics = None
    if scored:
        reference = TruthTrack.from_array(columns.truth)
        _place_odometry(tracks[2], reference)
        metrics = {
            "odometry": score(reference, tracks[2].t, tracks[2].x, tracks[2].y, tracks[2].theta),
            "ips": score_fixes(reference, fixes, offset),
            "paper_ekf": score(reference, tracks[1].t, tracks[1].x, tracks[1].y, tracks[1].theta),
            "ekf": score(reference, tracks[0].t, tracks[0].x, tracks[0].y, tracks[0].theta),
        }
    return ReplayResult(
        ekf=tracks[0],
        paper=tracks[1],
        odometry=tracks[2],
        fixes=fixes,
        metrics=metrics,
        counters=dict(robotd.counters),
        diagnostics=diagnostics,
        problems=list(log.problems) + problems,
        unknown_types=dict(log.unknown_types),
        geometry=geometry,
        ips_offset=offset,
        counts_per_rev=cpr,
    )


def _place(track: Track, x0: float, y0: float, theta0: float) -> None:
    """Move a track computed from (0, 0, 0) so that it starts at (x0, y0, theta0)."""
    c, s = math.cos(theta0), math.sin(theta0)
    for i in range(len(track.t)):
        x, y = track.x[i], track.y[i]
        track.x[i], track.y[i] = x0 + x * c - y * s, y0 + x * s + y * c
        track.theta[i] = (track.theta[i] + theta0 + math.pi) % (2.0 * math.pi) - math.pi


def _place_odometry(track: Track, truth: TruthTrack) -> None:
    """Put the odometry track on the true initial pose (evaluation only: the filters never see truth)."""
    if not track.t:
        return
    import numpy as np  # noqa: PLC0415 - only the evaluation needs it here

    t0 = np.array([track.t[0]])
    x0, y0, th0, _ = truth.at(t0)
    theta0 = float(th0[0])
    if not math.isfinite(theta0):
        # no true heading: the rotation that best lays the first metre of odometry onto the truth
        travelled = 0.0
        end = 1
        while end < len(track.t) and travelled < 1.0:
            travelled += math.hypot(track.x[end] - track.x[end - 1], track.y[end] - track.y[end - 1])
            end += 1
        tx, ty, _, _ = truth.at(np.array(track.t[:end]))
        theta0 = fit_rotation(list(zip(track.x[:end], track.y[:end], strict=True)), list(zip(tx, ty, strict=True)))[0]
    _place(track, float(x0[0]), float(y0[0]), theta0)


def write_outputs(result: ReplayResult, out_dir: Path) -> list[Path]:
    """Write estimates.jsonl (robotd's filter) and, with truth, metrics.json; returns the paths written."""
    out_dir.mkdir(parents=True, exist_ok=True)
    written = [out_dir / "estimates.jsonl"]
    e = result.ekf
    cov = np.asarray(e.cov, dtype=np.float64).reshape(-1, 6)[:, [0, 1, 2, 1, 3, 4, 2, 4, 5]]  # ekf.cov_full
    with open(written[0], "wb") as stream:
        write_estimates(stream, e.t, e.x, e.y, e.theta, cov)
    if result.metrics is not None:
        metrics = {name: (stats.as_dict() if stats is not None else None) for name, stats in result.metrics.items()}
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
    c = result.counters
    lines.append(
        f"fixes {c['fixes']}: accepted {c['fixes_accepted']}, rejected {c['fixes_rejected']}, "
        f"recoveries {c['recoveries']}, heading re-aligned {c['heading_realigned']}, lost {c['fixes_lost']}, "
        f"late {c['late_fixes']}, too old {c['fixes_too_old']}, "
        f"dropped {c['dropped_non_finite'] + c['dropped_out_of_order']}"
    )
    if result.unknown_types:
        lines.append("unknown event types: " + ", ".join(f"{k} x{v}" for k, v in sorted(result.unknown_types.items())))
    return "\n".join(lines)


__all__ = [
    "METHODS",
    "ReplayResult",
    "Track",
    "cyclic_gc_paused",
    "format_table",
    "replay",
    "robot_from_log",
    "write_outputs",
]
