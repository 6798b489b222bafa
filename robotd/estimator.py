"""robotd's pose estimator: the EKF of robotd.ekf wrapped in what a trustworthy filter needs. Pure: no I/O, no asyncio.

Theory of operation
- Inputs (wheel ticks or body twists) make prediction steps on the odometry track (robotd.track). Ticks are exact
  displacements: they are accumulated and become one step at their mean twist at most every `predict_period_s`.
  A twist is a sample held until the next.
- Fixes leave anchors on the track (robotd.history): the state at any time is the newest anchor before it carried
  forward in O(1). A fix measured at `t_meas` in the past is fused at that time, from the state there; the anchors
  after it are made again (a late fix lands exactly where an on-time one would, at a cost that does not depend on
  how late it is). Between steps the state moves with the twist of the step it falls in, and beyond the newest step
  with the twist of the ticks not yet integrated (or the twist in force).
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

import bisect
import math
from dataclasses import dataclass
from math import isfinite
from typing import Self

from robotd import ekf, kinematics
from robotd.config import EkfConfig
from robotd.fixgate import Diagnostics, FixGate, TrackState, Verdict
from robotd.heading import HeadingAligner, HeadingCheck, RotationFit
from robotd.history import Anchor, FixRecord, History, Predictor, State, Twist3
from robotd.track import OdometryTrack, displacement
from robotd.wheelsteps import TickKinematics, WheelFeed

# An initial heading standard deviation above this says the heading is unknown (the robot was put down anywhere).
HEADING_KNOWN_SIGMA_RAD = 0.5
TRIM_STEPS = 256  # the track is trimmed in batches: a few hundred steps are cheaper to keep than to cut often


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
        self._kinematics = TickKinematics(geometry, counts_per_rev)
        self._offset = ips_offset_m if (ekf_config.lever_arm and not paper) else (0.0, 0.0)
        self._latency = ekf_config.latency_compensation and not paper
        c = ekf_config
        if paper:  # eq. 9: a 2x2 on (v, w) mapped through G, per prediction step (see ekf.ControlNoise)
            noise = ekf.ControlNoise(const_v2=c.paper_sigma_v_mps**2, const_w2=c.paper_sigma_w_rad_s**2)
        else:
            noise = ekf.ControlNoise(
                lin2=c.odom_along_sigma_m**2,
                lat2=c.odom_across_sigma_m**2,
                slip2=c.slip_heading_sigma_rad**2,
                turn2=c.turn_heading_sigma_rad**2,
            )
        self._noise = noise
        self._track = OdometryTrack(noise, midpoint=not paper)
        self._predictor = Predictor(noise, midpoint=not paper)
        self._predictor.heading_known = paper or c.initial_sigma[2] <= HEADING_KNOWN_SIGMA_RAD
        x0, y0, th0 = c.initial_pose
        first = Anchor(-math.inf, x0, y0, ekf.wrap_angle(th0), ekf.cov_diag(*c.initial_sigma), None)
        self._history = History(self._track, self._predictor, first, c.history_s, keep_past=self._latency)
        self._last_accept_t = -math.inf
        self._wheels = WheelFeed(self._kinematics, c.predict_period_s)
        # the state at the newest step: (newest anchor, visible steps, state, whether the state is at that step)
        self._newest: tuple[Anchor, int, State, bool] | None = None
        self._aligner = HeadingAligner(c.heading_align_m, self._offset, enabled=c.heading_align_m > 0.0 and not paper)
        self._heading_check = HeadingCheck()
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
    def paper_filter(cls, ekf_config: EkfConfig, geometry: kinematics.Geometry, counts_per_rev: int) -> Self:
        """The paper's filter as published: no gating, fixes fused on arrival, no lever arm, R = s_ips^2 I."""
        return cls(ekf_config, geometry, (0.0, 0.0), counts_per_rev, paper=True)

    # --- inputs -----------------------------------------------------------------------------------

    def on_wheels(self, t: float, ticks: tuple[int, int, int, int]) -> None:
        """Cumulative encoder counts (FL FR RL RR) at time t."""
        wheels = self._wheels
        if not wheels.accepts(t):
            self.counters["dropped_out_of_order" if math.isfinite(t) else "dropped_non_finite"] += 1
            return
        self.counters["wheels"] += 1
        step = wheels.sample(t, ticks)
        if step is not None:
            self._step_to(step[0], step[1], step[1])

    def on_twist(self, t: float, vx: float, vy: float, wz: float) -> None:
        """A measured body twist (m/s, rad/s) at time t, held until the next one."""
        if not (math.isfinite(t) and math.isfinite(vx) and math.isfinite(vy) and math.isfinite(wz)):
            self.counters["dropped_non_finite"] += 1
            return
        if t < self._history.newest_step_t():
            self.counters["dropped_out_of_order"] += 1
            return
        self.counters["twists"] += 1
        track = self._track
        held = (track.hx[-1], track.hy[-1], track.hw[-1]) if len(track) else (0.0, 0.0, 0.0)
        self._step_to(t, held, (vx, vy, wz))

    def on_fix_lost(self, t: float) -> None:  # noqa: ARG002 - the daemon's interface carries the time
        """A position packet flagged "coordinates unavailable": never fused, only counted."""
        self.counters["fixes_lost"] += 1

    def _set_clock(self, t: float) -> None:
        """The first input or fix sets the clock: the initial state is at t."""
        first = self._history.anchors[0]
        self._history.reset(Anchor(t, first.x, first.y, first.theta, first.p, None))

    def _step_to(self, t: float, step_u: Twist3, held: Twist3) -> None:
        """A step ending at t with twist step_u, then `held` in force (the first input starts the track)."""
        track, history = self._track, self._history
        if not len(track):
            start = min(t, history.start) if history.start > -math.inf else t
            track.start(start, held if start == t else (0.0, 0.0, 0.0))
            if history.start == -math.inf:
                self._set_clock(start)
            if start < t:
                track.append(t, (0.0, 0.0, 0.0), held)
        elif t > track.t[-1]:
            track.append(t, step_u, held)
        else:
            track.hold(held)
        history.visible = len(track)
        if len(track) - TRIM_STEPS > 2 * TRIM_STEPS:
            needed = history.trim(t, self._pending)
            if needed > TRIM_STEPS:
                track.drop_before(track.first + needed)
                history.visible = len(track)
                self._newest = None  # its step index moved

    def _pending(self) -> Twist3:
        """The twist beyond the newest step: that of the samples fed since (their mean), or the one in force."""
        track, vis = self._track, self._history.visible
        u = self._wheels.pending()
        if u is not None:
            return u
        if not vis:
            return (0.0, 0.0, 0.0)
        return track.hx[vis - 1], track.hy[vis - 1], track.hw[vis - 1]

    # --- fixes ------------------------------------------------------------------------------------

    def on_fix(self, t: float, x: float, y: float, t_meas: float) -> Diagnostics | None:
        """An IPS fix of the beacon (m) that arrived at t and was measured at t_meas; returns its record."""
        counters = self.counters
        counters["fixes"] += 1
        if not (isfinite(t) and isfinite(x) and isfinite(y)):
            counters["dropped_non_finite"] += 1
            return None
        if not self._latency or not isfinite(t_meas) or t_meas > t:
            t_meas = t
        history = self._history
        if history.times[0] == -math.inf:
            self._set_clock(t_meas)
        vis = history.visible
        newest_step = self._track.t[vis - 1] if vis else -math.inf
        gate = self._fix_gate
        if t_meas < history.times[0] or (self._latency and t_meas < newest_step - self.config.history_s):
            counters["fixes_too_old"] += 1
            nan = math.nan
            return Diagnostics(
                t, t_meas, (nan, nan), (nan, nan, nan), nan, gate.gate, Verdict.TOO_OLD, math.sqrt(gate.r)
            )
        anchors = history.anchors
        k = bisect.bisect_right(history.times, t_meas) - 1
        if t_meas < newest_step or k < len(anchors) - 1:
            counters["late_fixes"] += 1
        prior = history.state_at(anchors[k], t_meas, self._pending)
        px, py, pth, pp = prior
        r = gate.r
        inn = ekf.innovation(px, py, pth, pp, x, y, r, self._offset[0], self._offset[1])
        verdict = gate.judge(t_meas, inn, r)
        aligner = self._aligner
        if aligner.enabled and gate.seeded:
            if aligner.start_t == math.inf:
                self._restart_window()  # the first window starts with the first seeded fix
            aligner.record(x, y, t_meas, self._track.pose_at(t_meas, history.visible))
        if verdict is Verdict.ACCEPTED:
            anchor = self._fuse(prior, t_meas, (x, y, r), inn)
        elif verdict is Verdict.SEEDED or verdict is Verdict.RECOVERED:
            anchor = self._seed(prior, t_meas, (x, y, r), verdict)
        else:
            anchor = Anchor(t_meas, px, py, pth, pp, FixRecord(x, y, r, fused=False))
        history.place(k, anchor, self._remake, self._pending)  # every later anchor again, from the corrected state
        if verdict is Verdict.ACCEPTED or verdict is Verdict.SEEDED or verdict is Verdict.RECOVERED:
            self._last_accept_t = max(self._last_accept_t, t_meas)
        if aligner.enabled and vis and self._track.dist[vis - 1] >= aligner.next_fit:
            self._maybe_realign()
        return Diagnostics(
            t, t_meas, (inn.nu_x, inn.nu_y), (inn.s_xx, inn.s_xy, inn.s_yy), inn.nis, gate.gate, verdict, math.sqrt(r)
        )

    def _remake(self, state: State, old: Anchor) -> Anchor:
        """An anchor made again at its time from the state there: its fix fused again, its seed moved again."""
        fix = old.fix
        x, y, th, p = state
        if fix is None:
            return Anchor(old.t, x, y, th, p, None)
        if fix.fused:
            inn = ekf.innovation(x, y, th, p, fix.zx, fix.zy, fix.r, *self._offset)
            return self._fuse(state, old.t, (fix.zx, fix.zy, fix.r), inn)
        if fix.seed is not None:
            r = fix.r
            return Anchor(old.t, x + fix.seed[0], y + fix.seed[1], th, (r, 0.0, 0.0, r, 0.0, p[5]), fix)
        return Anchor(old.t, x, y, th, p, fix)

    def _fuse(self, prior: State, t: float, z: tuple[float, float, float], inn: ekf.Innovation) -> Anchor:
        """The anchor of fix z = (zx, zy, r) fused at t into the prior."""
        # at rest a fix says nothing about the heading; with the heading unknown the model has no heading to correct
        if self.paper:
            freeze = False
        elif not self._predictor.heading_known:
            freeze = True
        else:
            u = self._track.twist_at(t, self._history.visible) or self._pending()
            freeze = math.hypot(u[0], u[1]) < self.config.heading_min_speed_mps
        x, y, th, p = ekf.update(prior[0], prior[1], prior[2], prior[3], inn, z[2], freeze_heading=freeze)
        return Anchor(t, x, y, th, p, FixRecord(z[0], z[1], z[2], fused=True))

    def _seed(self, prior: State, t: float, z: tuple[float, float, float], verdict: Verdict) -> Anchor:
        """Move the beacon onto the agreeing fixes (their median innovation), forgetting the position's past."""
        if verdict is Verdict.RECOVERED:
            self._restart_window()  # carried robots may have been turned too: check the heading again
            self._heading_check.forget()
            self._predictor.heading_known = False
        dx, dy = self._fix_gate.seed_shift(verdict)
        zx, zy, r = z
        p = (r, 0.0, 0.0, r, 0.0, prior[3][5])
        return Anchor(t, prior[0] + dx, prior[1] + dy, prior[2], p, FixRecord(zx, zy, r, fused=False, seed=(dx, dy)))

    # --- heading alignment --------------------------------------------------------------------------

    def _restart_window(self) -> None:
        t, pose, dist = self._track.newest(self._history.visible, self._history.start)
        self._aligner.restart(t, pose, dist)

    def _maybe_realign(self) -> None:
        """Take the heading of the aligner's rotation fit when the filter's heading disagrees with it."""
        now_t, now_pose, dist = self._track.newest(self._history.visible, self._history.start)
        # an unknown heading is taken from a whole window: the longer the track, the better its direction
        known = self._predictor.heading_known
        fit = self._aligner.check(self._fix_gate.r, now_t, now_pose, dist, whole=not known)
        if fit is None:
            return
        _, _, theta, p = self._state_at_newest_step()
        if self._heading_check.realign(fit, theta, p[5], heading_known=known):
            self._realign(fit)

    def _realign(self, fit: RotationFit) -> None:
        """Restart the state from the window's fit: its heading, and the position its translation puts it at."""
        ax, ay, ath = fit.window_odo
        sigma = fit.sigma
        self._predictor.heading_known = True
        self.counters["heading_realigned"] += 1
        c, s = math.cos(fit.rotation), math.sin(fit.rotation)
        x, y = fit.tx + ax * c - ay * s, fit.ty + ax * s + ay * c
        r = self._fix_gate.r
        when = self._history.newest_step_t()
        anchor = Anchor(when, x, y, ekf.wrap_angle(fit.rotation + ath), (r, 0.0, 0.0, r, 0.0, sigma * sigma), None)
        # the states before now were built on the wrong heading: start again from here
        self._history.reset(anchor)
        self._fix_gate.forget()
        self._restart_window()

    # --- output ---------------------------------------------------------------------------------------

    def _state_at_newest_step(self) -> State:
        """The state at the newest visible step, or at the newest anchor when that is later."""
        history = self._history
        anchor, vis = history.newest, history.visible
        cached = self._newest
        if cached is not None and cached[0] is anchor:
            if cached[1] == vis:
                return cached[2]
            if cached[3] and cached[1] < vis <= cached[1] + 2:
                # the outputs between two fixes: one or two steps on from the last output, taken one by one
                track, move = self._track, self._predictor.move
                state = cached[2]
                for k in range(cached[1], vis):
                    state = move(state, (track.vx[k], track.vy[k], track.wz[k]), track.t[k] - track.t[k - 1])
                self._newest = (anchor, vis, state, True)
                return state
        when = history.newest_step_t()
        on_step = when > anchor.t
        state = history.state_at(anchor, when, self._pending) if on_step else anchor.state
        self._newest = (anchor, vis, state, on_step)
        return state

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
        _, x, y, th, _, p = self._extrapolate(t)
        return x, y, th, p

    def _extrapolate(self, t: float | None) -> tuple[float, float, float, float, Twist3, ekf.Cov]:
        """Time, pose, twist in force and P of the newest state carried forward to t (mean only) when t is later."""
        history = self._history
        when = max(history.newest_step_t(), history.newest.t)
        x, y, th, p = self._state_at_newest_step()
        u = self._pending()
        if t is None:
            t = max(when, self._wheels.last_t)
        if t > when and math.isfinite(when):
            vx, vy, wz = u
            dt = t - when
            dx, dy, _, _ = displacement(vx, vy, wz, dt, th, midpoint=True, lib=math)
            x, y = x + dx, y + dy
            th = ekf.wrap_angle(th + wz * dt)
            when = t
        return when, x, y, th, u, p


__all__ = ["Diagnostics", "Estimator", "PoseEstimate", "TrackState", "Verdict"]
