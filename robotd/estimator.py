"""robotd's pose estimator: the EKF of robotd.ekf wrapped in what a trustworthy filter needs. Pure: no I/O, no asyncio.

Theory of operation
- Inputs (wheel ticks or body twists) advance the state. Ticks are exact displacements: they are accumulated and
  integrated at most every `predict_period_s` as one step at their mean twist. A twist is a sample held until the next.
- Each step is kept in a short history (robotd.history: state, covariance, twist in force, and the event that
  produced it). A fix measured at `t_meas` in the past is fused at that time: the history is rewound to the last
  state before `t_meas`, the fix is fused there, and every later event is applied again (a late fix lands exactly
  where an on-time one would).
- Each fix gets a verdict (robotd.fixgate): the first agreeing fixes seed the position, then fixes are gated by their
  NIS (chi-square, 2 dof); rejected fixes that keep coming for `recovery_min_s` and agree with each other once the
  odometry motion is removed re-seed the position (the robot was carried, or the filter drifted). The IPS noise is
  estimated from the median of recent innovations, robust to outliers, between two bounds.
- The heading is checked once the robot has driven `heading_align_m` (robotd.heading): the odometry track is rotated
  onto the fixes (a least-squares rotation); when that rotation disagrees with the filter, the filter takes it. An
  unknown initial heading therefore costs one short drive, not a lost robot.
- The paper's filter is the same code with those features off (`Estimator.paper_filter`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from robotd import ekf, kinematics
from robotd.config import EkfConfig
from robotd.fixgate import FixGate, TrackState, Verdict
from robotd.heading import HeadingAligner, RotationFit
from robotd.history import Entry, History, Predictor, Twist3, initial_entry

# An initial heading standard deviation above this says the heading is unknown (the robot was put down anywhere).
HEADING_KNOWN_SIGMA_RAD = 0.5
MIN_REALIGN_RAD = 0.35  # smaller heading errors are the EKF's own business: it corrects them from fixes in motion


@dataclass(frozen=True, slots=True)
class Diagnostics:
    """One fix's record: innovation nu, its covariance S (xx, xy, yy), NIS, the gate, the verdict."""

    t: float
    t_meas: float
    nu: tuple[float, float]
    s: tuple[float, float, float]
    nis: float
    gate: float
    verdict: Verdict
    r_m: float

    @property
    def accepted(self) -> bool:
        """Whether the fix moved the estimate."""
        return self.verdict in (Verdict.ACCEPTED, Verdict.SEEDED, Verdict.RECOVERED)


@dataclass(frozen=True, slots=True)
class PoseEstimate:
    """The estimate at time t: pose, body twist in force, 3x3 covariance row-major, age of the last accepted fix."""

    t: float
    x: float
    y: float
    theta: float
    vx: float
    vy: float
    wz: float
    cov: tuple[float, float, float, float, float, float, float, float, float]
    fix_age_s: float
    state: TrackState


class Estimator:
    """Pose estimation from wheel odometry and IPS fixes (see the module docstring)."""

    def __init__(
        self,
        ekf_config: EkfConfig,
        geometry: kinematics.Geometry,
        ips_offset_m: tuple[float, float],
        counts_per_rev: int,
        *,
        paper: bool = False,
    ) -> None:
        self.config = ekf_config
        self.geometry = geometry
        self.counts_per_rev = counts_per_rev
        self.paper = paper
        self._r4 = geometry.wheel_radius_m / 4.0
        self._r4k = geometry.wheel_radius_m / (4.0 * (geometry.lx_m + geometry.ly_m))
        self._offset = ips_offset_m if (ekf_config.lever_arm and not paper) else (0.0, 0.0)
        self._latency = ekf_config.latency_compensation and not paper
        c = ekf_config
        if paper:  # eq. 9: a 2x2 on (v, w) mapped through G, per prediction step (see ekf.ControlNoise)
            self._noise = ekf.ControlNoise(const_v2=c.paper_sigma_v_mps**2, const_w2=c.paper_sigma_w_rad_s**2)
        else:
            self._noise = ekf.ControlNoise(
                lin2=c.odom_along_sigma_m**2,
                lat2=c.odom_across_sigma_m**2,
                slip2=c.slip_heading_sigma_rad**2,
                turn2=c.turn_heading_sigma_rad**2,
            )
        self._predictor = Predictor(self._noise, midpoint=not paper)
        self._predictor.heading_known = paper or c.initial_sigma[2] <= HEADING_KNOWN_SIGMA_RAD
        self._history = History(
            initial_entry(c.initial_pose, ekf.cov_diag(*c.initial_sigma)), c.history_s, keep_past=self._latency
        )
        self._last_accept_t = -math.inf
        self._last_input_t = -math.inf
        # wheel ticks accumulated since the last prediction
        self._tick_base: tuple[int, int, int, int] | None = None
        self._tick_base_t = -math.inf
        self._tick_last: tuple[int, int, int, int] | None = None
        self._tick_last_t = -math.inf
        self._aligner = HeadingAligner(c.heading_align_m, self._offset, enabled=c.heading_align_m > 0.0 and not paper)
        # Whether a window's fit has agreed with the filter's heading since start-up (or since the robot was carried):
        # until then the heading is unknown and one disagreeing window re-aligns it; after it, a window that
        # disagrees is only a suspect (an echo or a slip can bend one window), confirmed by the next window.
        self._heading_confirmed = False
        self._suspect: tuple[int, float, float] | None = None  # (window, signed disagreement, its sigma)
        self.counters: dict[str, int] = dict.fromkeys(
            (
                "wheels",
                "twists",
                "fixes",
                "fixes_accepted",
                "fixes_rejected",
                "fixes_seeded",
                "recoveries",
                "heading_realigned",
                "fixes_lost",
                "dropped_non_finite",
                "dropped_out_of_order",
                "fixes_too_old",
                "late_fixes",
            ),
            0,
        )
        self._fix_gate = FixGate(c, self.counters, paper=paper)

    @classmethod
    def paper_filter(cls, ekf_config: EkfConfig, geometry: kinematics.Geometry, counts_per_rev: int) -> Estimator:
        """The paper's filter as published: no gating, fixes fused on arrival, no lever arm, R = s_ips^2 I."""
        return cls(ekf_config, geometry, (0.0, 0.0), counts_per_rev, paper=True)

    # --- inputs -----------------------------------------------------------------------------------

    def on_wheels(self, t: float, ticks: tuple[int, int, int, int]) -> None:
        """Cumulative encoder counts (FL FR RL RR) at time t."""
        if not math.isfinite(t) or t <= self._tick_last_t:
            self.counters["dropped_out_of_order" if math.isfinite(t) else "dropped_non_finite"] += 1
            return
        self.counters["wheels"] += 1
        if self._tick_base is None:
            self._tick_base, self._tick_base_t = ticks, t
            self._tick_last, self._tick_last_t = ticks, t
            self._input_step(t, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
            return
        self._tick_last, self._tick_last_t = ticks, t
        if t - self._tick_base_t >= self.config.predict_period_s:
            self._flush_ticks()

    def on_wheel_samples(
        self, times: list[float], ticks: list[tuple[int, int, int, int]], start: int, stop: int
    ) -> None:
        """on_wheels(times[i], ticks[i]) for i in range(start, stop), in one call: the same result, faster.

        Most samples only move the newest tick reading; this loop keeps that reading in local variables and does
        the full work only for the samples that end a prediction step (or that on_wheels would drop).
        """
        if self._tick_base is None:  # the first sample starts the tick clock: the general path
            while start < stop and self._tick_base is None:
                self.on_wheels(times[start], ticks[start])
                start += 1
        last_t, base_t = self._tick_last_t, self._tick_base_t
        period = self.config.predict_period_s
        newest = -1  # the newest sample taken but not yet stored in self._tick_last
        taken = 0
        for i in range(start, stop):
            t = times[i]
            if last_t < t < math.inf:
                taken += 1
                last_t = t
                newest = i
                if t - base_t >= period:
                    self._tick_last, self._tick_last_t = ticks[i], t
                    self._flush_ticks()
                    base_t = t
                    newest = -1
                continue
            if newest >= 0:
                self._tick_last, self._tick_last_t = ticks[newest], last_t
                newest = -1
            self.on_wheels(t, ticks[i])  # dropped: counted there
        if newest >= 0:
            self._tick_last, self._tick_last_t = ticks[newest], last_t
        self.counters["wheels"] += taken

    def on_twist(self, t: float, vx: float, vy: float, wz: float) -> None:
        """A measured body twist (m/s, rad/s) at time t, held until the next one."""
        if not (math.isfinite(t) and math.isfinite(vx) and math.isfinite(vy) and math.isfinite(wz)):
            self.counters["dropped_non_finite"] += 1
            return
        if t < self._history.last.t:
            self.counters["dropped_out_of_order"] += 1
            return
        self.counters["twists"] += 1
        self._input_step(t, self._history.last.u, (vx, vy, wz))

    def on_fix_lost(self, t: float) -> None:  # noqa: ARG002 - the daemon's interface carries the time
        """A position packet flagged "coordinates unavailable": never fused, only counted."""
        self.counters["fixes_lost"] += 1

    def _flush_ticks(self) -> None:
        """Integrate the ticks accumulated since the last prediction as one step at their mean twist."""
        base, last = self._tick_base, self._tick_last
        assert base is not None
        assert last is not None
        dt = self._tick_last_t - self._tick_base_t
        if dt <= 0.0:
            return
        k = 2.0 * math.pi / self.counts_per_rev / dt
        w1, w2, w3, w4 = (
            (last[0] - base[0]) * k,
            (last[1] - base[1]) * k,
            (last[2] - base[2]) * k,
            (last[3] - base[3]) * k,
        )
        # kinematics.forward (eq. 1), inlined: this runs for every prediction step
        u = (self._r4 * (w1 + w2 + w3 + w4), self._r4 * (-w1 + w2 + w3 - w4), self._r4k * (-w1 + w2 - w3 + w4))
        self._tick_base, self._tick_base_t = last, self._tick_last_t
        self._input_step(self._tick_last_t, u, u)

    def _input_step(self, t: float, step_u: Twist3, next_u: Twist3) -> None:
        last = self._history.last
        if last.t == -math.inf:  # the first input only sets the clock
            self._history.set_last_time(t)
            last.u = next_u
            self._last_input_t = t
            return
        t = max(t, last.t)  # a fix may have carried the state past this input's time
        self._aligner.track(step_u, t - last.t, t)
        self._history.append(self._predictor.input_step(last, t, step_u, next_u))
        self._last_input_t = t

    # --- fixes ------------------------------------------------------------------------------------

    def on_fix(self, t: float, x: float, y: float, t_meas: float) -> Diagnostics | None:
        """An IPS fix of the beacon (m) that arrived at t and was measured at t_meas; returns its record."""
        self.counters["fixes"] += 1
        if not (math.isfinite(t) and math.isfinite(x) and math.isfinite(y)):
            self.counters["dropped_non_finite"] += 1
            return None
        if self._tick_base is not None and self._tick_last_t > self._tick_base_t:
            self._flush_ticks()  # the state must reach the newest input before a fix is placed in time
        if not self._latency or not math.isfinite(t_meas):
            t_meas = t
        t_meas = min(t_meas, t)
        history = self._history
        if history.last.t == -math.inf:
            history.set_last_time(t_meas)
        if t_meas < history.start:
            self.counters["fixes_too_old"] += 1
            return Diagnostics(
                t,
                t_meas,
                (math.nan, math.nan),
                (math.nan,) * 3,
                math.nan,
                self._fix_gate.gate,
                Verdict.TOO_OLD,
                math.sqrt(self._fix_gate.r),
            )
        k = history.index_at(t_meas)
        if k < len(history.entries) - 1:
            self.counters["late_fixes"] += 1
        base = history.entries[k]
        prior = self._predictor.step(base, t_meas, base.u) if t_meas > base.t else base
        ox, oy = self._offset
        gate = self._fix_gate
        r = gate.r
        inn = ekf.innovation(prior.x, prior.y, prior.theta, prior.p, x, y, r, ox, oy)
        verdict = gate.judge(t_meas, inn, r)
        if gate.seeded:
            self._aligner.record(x, y, t_meas)
        if verdict is Verdict.ACCEPTED:
            fused = self._fuse(prior, x, y, r, inn)
        elif verdict is Verdict.SEEDED or verdict is Verdict.RECOVERED:
            fused = self._seed(prior, x, y, r, verdict)
        else:
            fused = Entry(t_meas, prior.x, prior.y, prior.theta, prior.p, prior.u, None, (x, y, r, False))
        history.rewrite(k, fused, self._replay_event)  # every later event again, from the corrected state
        if verdict is Verdict.SEEDED or verdict is Verdict.RECOVERED or verdict is Verdict.ACCEPTED:
            self._last_accept_t = max(self._last_accept_t, t_meas)
        self._maybe_realign()
        return Diagnostics(
            t,
            t_meas,
            (inn.nu_x, inn.nu_y),
            (inn.s_xx, inn.s_xy, inn.s_yy),
            inn.nis,
            self._fix_gate.gate,
            verdict,
            math.sqrt(r),
        )

    def _replay_event(self, prev: Entry, event: Entry) -> Entry:
        if event.fix is not None:
            zx, zy, r, was_fused = event.fix
            moved = self._predictor.step(prev, event.t, prev.u)
            moved.u = prev.u
            if not was_fused:
                moved.fix = event.fix
                return moved
            inn = ekf.innovation(moved.x, moved.y, moved.theta, moved.p, zx, zy, r, *self._offset)
            return self._fuse(moved, zx, zy, r, inn)
        assert event.step_u is not None
        return self._predictor.input_step(prev, event.t, event.step_u, event.u)

    def _fuse(self, prior: Entry, zx: float, zy: float, r: float, inn: ekf.Innovation) -> Entry:
        # at rest a fix says nothing about the heading; with the heading unknown the model has no heading to correct
        slow = math.hypot(prior.u[0], prior.u[1]) < self.config.heading_min_speed_mps
        freeze = (slow or not self._predictor.heading_known) and not self.paper
        x, y, th, p = ekf.update(prior.x, prior.y, prior.theta, prior.p, inn, r, freeze_heading=freeze)
        return Entry(prior.t, x, y, th, p, prior.u, None, (zx, zy, r, True))

    def _seed(self, prior: Entry, zx: float, zy: float, r: float, verdict: Verdict) -> Entry:
        """Move the beacon onto the agreeing fixes (their median innovation), forgetting the position's past."""
        if verdict is Verdict.RECOVERED:
            self._aligner.restart()  # carried robots may have been turned too: check the heading again
            self._heading_confirmed = False
            self._predictor.heading_known = False
        dx, dy = self._fix_gate.seed_shift(verdict)
        p = (r, 0.0, 0.0, r, 0.0, prior.p[5])
        return Entry(prior.t, prior.x + dx, prior.y + dy, prior.theta, p, prior.u, None, (zx, zy, r, False))

    # --- heading alignment --------------------------------------------------------------------------

    def _maybe_realign(self) -> None:
        """Take the heading of the aligner's rotation fit when the filter's heading disagrees with it."""
        # an unknown heading is taken from a whole window: the longer the track, the better its direction
        fit = self._aligner.check(self._fix_gate.r, whole=not self._predictor.heading_known)
        if fit is None:
            return
        last = self._history.last
        # the filter's heading at the window's start is its current heading less the odometry turn since
        ath = fit.window_odo[2]
        filter_start = ekf.wrap_angle(last.theta - ath)
        signed = ekf.wrap_angle(fit.rotation - filter_start)
        sigma = fit.sigma
        if sigma > 0.15:
            return
        if not self._predictor.heading_known:
            self._realign(fit)  # the first trustworthy window gives the heading that was unknown
            return
        if abs(signed) <= max(4.0 * math.sqrt(sigma * sigma + last.p[5]), MIN_REALIGN_RAD):
            if abs(signed) <= 3.0 * math.sqrt(sigma * sigma + last.p[5]):
                self._heading_confirmed = True
                self._suspect = None
            return
        if self._heading_confirmed:
            suspect, window = self._suspect, fit.window
            if suspect is None or suspect[0] == window:
                if suspect is None:
                    self._suspect = (window, signed, sigma)
                return
            if abs(ekf.wrap_angle(signed - suspect[1])) > 3.0 * math.hypot(sigma, suspect[2]):
                self._suspect = (window, signed, sigma)  # two windows that disagree with each other: neither is proof
                return
        self._realign(fit)

    def _realign(self, fit: RotationFit) -> None:
        """Restart the state from the window's fit: its heading, and the position its translation puts it at."""
        last = self._history.last
        ax, ay, ath = fit.window_odo
        sigma = fit.sigma
        self._suspect = None
        self._predictor.heading_known = True
        self.counters["heading_realigned"] += 1
        c, s = math.cos(fit.rotation), math.sin(fit.rotation)
        x, y = fit.tx + ax * c - ay * s, fit.ty + ax * s + ay * c
        r = self._fix_gate.r
        entry = Entry(
            last.t, x, y, ekf.wrap_angle(fit.rotation + ath), (r, 0.0, 0.0, r, 0.0, sigma * sigma), last.u, None, None
        )
        # the history before now was built on the wrong heading: start it again from here
        self._history.reset(entry)
        self._fix_gate.forget()
        self._aligner.restart()

    # --- output ---------------------------------------------------------------------------------------

    def pose(self, t: float | None = None) -> PoseEstimate:
        """The estimate, extrapolated with the twist in force to time t when t is later than the newest input."""
        when, x, y, th, (vx, vy, wz), p = self._extrapolate(t)
        return PoseEstimate(
            when, x, y, th, vx, vy, wz, ekf.cov_full(p), when - self._last_accept_t, self._fix_gate.state
        )

    def position(self, t: float) -> tuple[float, float, float, ekf.Cov] | None:
        """x, y, theta and P (upper triangle) of pose(t), or None before a fix placed the filter (state INITIALISING).

        The replay's per-output call: the same numbers as pose(t) without building a PoseEstimate.
        """
        if self._fix_gate.state is TrackState.INITIALISING:
            return None
        last = self._history.entries[-1]
        if t > last.t > -math.inf:  # carried forward: the arithmetic of _extrapolate
            _, x, y, th, _, p = self._extrapolate(t)
            return x, y, th, p
        return last.x, last.y, last.theta, last.p

    def _extrapolate(self, t: float | None) -> tuple[float, float, float, float, Twist3, ekf.Cov]:
        """Time, pose, twist in force and P of the newest state carried forward to t (see pose)."""
        last = self._history.last
        x, y, th = last.x, last.y, last.theta
        when = last.t
        u = last.u
        base, ticks = self._tick_base, self._tick_last
        if base is not None and ticks is not None and self._tick_last_t > self._tick_base_t:
            # ticks not yet integrated: their mean twist, without committing a prediction step
            k = 2.0 * math.pi / self.counts_per_rev / (self._tick_last_t - self._tick_base_t)
            w1, w2, w3, w4 = (
                (ticks[0] - base[0]) * k,
                (ticks[1] - base[1]) * k,
                (ticks[2] - base[2]) * k,
                (ticks[3] - base[3]) * k,
            )
            u = (self._r4 * (w1 + w2 + w3 + w4), self._r4 * (-w1 + w2 + w3 - w4), self._r4k * (-w1 + w2 - w3 + w4))
        if t is None:
            t = max(when, self._tick_last_t)
        if t > when and math.isfinite(when):
            vx, vy, wz = u
            dt = t - when
            mid = th + 0.5 * wz * dt
            c, s = math.cos(mid), math.sin(mid)
            x, y = x + (vx * c - vy * s) * dt, y + (vx * s + vy * c) * dt
            th = ekf.wrap_angle(th + wz * dt)
            when = t
        return when, x, y, th, u, last.p


__all__ = ["Diagnostics", "Estimator", "PoseEstimate", "TrackState", "Verdict"]
