"""robotd's pose estimator: the EKF of robotd.estimation.ekf wrapped in what a trustworthy filter needs. Pure: no I/O,
no asyncio.

Theory of operation
- Inputs (wheel ticks or body twists) make prediction steps on the odometry track (robotd.estimation.track). Ticks are
  exact displacements: they are accumulated and become one step at their mean twist at most every `predict_period_s`.
  A twist is a sample held until the next.
- Fixes leave anchors on the track (robotd.estimation.history): the state at any time is the newest anchor before it
  carried forward through the steps since. A fix measured at `t_meas` in the past is fused at that time, from the state
  there; the anchors after it are made again (a late fix lands exactly where an on-time one would). Between steps the
  state moves with the twist of the step it falls in, and beyond the newest step with the twist of the ticks not yet
  integrated (or the twist in force).
- Each fix gets a verdict (robotd.estimation.fixgate): the first agreeing fixes seed the position, then fixes are gated
  by their NIS (chi-square, 2 dof); rejected fixes that keep coming for `recovery_min_s` and agree with each other once
  the odometry motion is removed re-seed the position (the robot was carried, or the filter drifted). The IPS noise is
  estimated from the median of recent innovations, robust to outliers, between two bounds. The odometry noise is the
  configuration's times the scales (position, heading) that make the fixes likeliest for a bank of shadow filters
  (robotd.estimation.process_noise) while the fixes are judged independent.
- The heading is checked once the robot has driven `heading_align_m` (robotd.estimation.heading): the odometry track is
  rotated onto the fixes (a least-squares rotation); when that rotation disagrees with the filter, the filter takes it.
  An unknown initial heading therefore costs one short drive, not a lost robot.
- Where the position and the heading stand (placed or not, tracking or rejecting; heading unknown, aligned,
  confirmed or suspect) is one state machine, robotd.estimation.modes.
- The paper's filter is the same code configured with those features off (robotd.config.model.paper_preset).
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass
from math import isfinite

from robotd import kinematics
from robotd.config.model import EkfConfig
from robotd.estimation import ekf
from robotd.estimation.calibration import TAU_K, Calibration, CalibrationLimits, Calibrator
from robotd.estimation.fixgate import Diagnostics, FixGate
from robotd.estimation.heading import HeadingAligner, HeadingCheck, RotationFit
from robotd.estimation.history import (
    ACCEL_DENSITY,
    ANGULAR_ACCEL_DENSITY,
    NO_ODOMETRY_SPEED_VAR,
    NO_ODOMETRY_TURN_VAR,
    NO_PROVISIONAL_HEADING,
    Anchor,
    FixRecord,
    History,
    Predictor,
    State,
)
from robotd.estimation.modes import Modes, PositionMode, Verdict
from robotd.estimation.process_noise import OdometryNoise, Pose, ProcessNoiseScale, Travel
from robotd.estimation.track import OdometryTrack, Twist3
from robotd.estimation.wheelsteps import TickKinematics, WheelFeed

LATENCY_PRIOR_SIGMA_S = 0.1  # how far the delay of fixes without a measurement time may be from the assumed one
TIME_CHECK_SIGMA_S = 0.03  # how far a fix's stated measurement time may be off
# a rotation fit's sigma is first order (sin s ~ s, 4 % off at 0.5 rad, 10 % at 0.8): beyond it, no guide (a short
# track's fit at 0.8 was a wrong direction on the libRSF start, one at 0.3+ was once 5 sigma off)
PROVISIONAL_MAX_SIGMA_RAD = 0.5
# the fewest fixes a provisional heading is fitted from: three (six coordinates for a rotation and a translation);
# waiting for five left a 4 Hz beacon's robot a second of driving without one
PROVISIONAL_MIN_FIXES = 3
# a twist's stamp marks the start, the middle or the end of the interval the sample averages (no log says which): the
# three equally likely put the motion's true time within +-half a period of the stamp, variance period^2 / 6
STAMP_CONVENTION_VAR = 1.0 / 6.0
# an odometry stream whose next sample comes this many periods late, and at least PAUSE_MIN_S, has paused: the motion in
# the gap is a guess (a loop that stalls a few tens of milliseconds on a busy Pi is not a pause)
STREAM_PAUSE_PERIODS = 3.0
PAUSE_MIN_S = 0.25
TRIM_STEPS = 256  # the track is trimmed in batches: a few hundred steps are cheaper to keep than to cut often
# and the anchors too when the track does not grow: odometry that is silent (a robot at rest whose stream publishes
# only changes, an unplugged encoder) while fixes keep coming would otherwise keep every fix's anchor for ever
TRIM_ANCHORS = 512


@dataclass(frozen=True, slots=True)
class PoseEstimate:
    """The estimate at time t: pose, body twist in force, 3x3 covariance row-major, the time since the measurement
    of the newest fix that moved the estimate (fix_age_s), and the position mode."""

    t: float
    x: float
    y: float
    theta: float
    vx: float
    vy: float
    wz: float
    cov: tuple[float, float, float, float, float, float, float, float, float]
    fix_age_s: float
    state: PositionMode


@dataclass(frozen=True, slots=True)
class LearntNoise:
    """The noise the filter learnt, kept across restarts beside the calibration: the IPS noise variance per axis in
    use (m^2) and the factors on the configured odometry noise variances, the position terms' and the heading's."""

    ips_var: float
    process_noise_scale: float = 1.0
    heading_noise_scale: float = 1.0


@dataclass(frozen=True, slots=True)
class _FixToLearn:
    """A fix that was fused, or not, and what the filter has yet to learn from it (Estimator.settle)."""

    verdict: Verdict
    t_meas: float
    inn: ekf.Innovation
    r: float
    prior: State
    anchor: Anchor
    stated: float
    x: float
    y: float
    timed: bool
    travel: Travel  # the odometry's at t_meas


class StreamPace:
    """An odometry stream's sampling interval (a running mean of the gaps between its samples), and how late a sample
    may come before the stream has paused."""

    __slots__ = ("interval_s", "pause_after_s")

    def __init__(self) -> None:
        self.interval_s = 0.0
        self.pause_after_s = math.inf  # until the interval is known

    def paused_by(self, gap: float, floor_s: float = 0.0) -> bool:
        """Whether a sample `gap` after the one before ends a pause; otherwise the gap joins the interval (taken as at
        least floor_s: a stream read in steps of that length)."""
        if gap > self.pause_after_s:
            return True
        if 0.0 < gap < 1.0:  # a longer gap is a pause in the stream, not its interval
            interval = gap if self.interval_s == 0.0 else 0.9 * self.interval_s + 0.1 * gap
            self.interval_s = interval
            self.pause_after_s = max(STREAM_PAUSE_PERIODS * max(interval, floor_s), PAUSE_MIN_S)
        return False

    def bridge(self, gap: float) -> float:
        """The variance factor of the motion in a pause of `gap` beyond one interval: (gap^3 - interval^3) / 12, times
        an acceleration density (robotd.estimation.history: a velocity pinned at both ends)."""
        return (gap**3 - self.interval_s**3) / 12.0


class Estimator:
    """Pose estimation from wheel odometry and IPS fixes (see the module docstring)."""

    def __init__(
        self,
        ekf_config: EkfConfig,
        geometry: kinematics.Geometry,
        ips_offset_m: tuple[float, float],
        counts_per_rev: int,
        *,
        default_latency_s: float = 0.05,
        calibration: Calibration | None = None,
        noise: LearntNoise | None = None,
    ) -> None:
        """`default_latency_s`: the delay assumed at first for fixes without a measurement time; `calibration`: where
        the odometry calibration starts (a saved one), else from the configuration; `noise`: where the learnt noise
        starts (a saved one, used only with a calibration that has judged the fixes), else from the configuration."""
        c = self.config = ekf_config
        self.geometry = geometry
        self.counts_per_rev = counts_per_rev
        self._offset = ips_offset_m if c.lever_arm else (0.0, 0.0)
        control_noise = ekf.ControlNoise(
            lin2=c.odom_along_sigma_m**2,
            lat2=c.odom_across_sigma_m**2,
            slip2=c.slip_heading_sigma_rad**2,
            turn2=c.turn_heading_sigma_rad**2,
            const_v2=c.step_sigma_v_mps**2,
            const_w2=c.step_sigma_w_rad_s**2,
            spin2=c.odom_turn_sigma_m**2,
        )
        self.modes = Modes(heading_known=c.initial_sigma[2] <= c.unknown_heading_sigma_rad)
        self._track = OdometryTrack(midpoint=c.midpoint_heading)
        self._predictor = Predictor(control_noise, self.modes, midpoint=c.midpoint_heading)
        if calibration is None:
            kx, ky, kw = c.odometry_scale
            sigmas = (c.scale_sigma, c.scale_sigma, c.scale_sigma, LATENCY_PRIOR_SIGMA_S, TIME_CHECK_SIGMA_S)
            calibration = Calibration(kx, ky, kw, default_latency_s, 0.0, sigmas)
        self._calibrator: Calibrator | None = None
        if c.calibrate:
            limits = CalibrationLimits(c.scale_limit, c.latency_max_s, c.calibration_window_m)
            self._calibrator = Calibrator(calibration, limits, self._offset)
            calibration = self._calibrator.current
        else:
            sigmas = (0.0, 0.0, 0.0, 0.0, 0.0)
            calibration = Calibration(*c.odometry_scale, default_latency_s, 0.0, sigmas)
        self._calibration = calibration
        x0, y0, th0 = c.initial_pose
        first = Anchor(-math.inf, x0, y0, ekf.wrap_angle(th0), ekf.cov_diag(*c.initial_sigma), None)
        self._history = History(self._track, self._predictor, first, c.history_s, keep_past=c.latency_compensation)
        self._use_scales(calibration)
        self._noise_to_calibrator()
        self._last_accept_t = -math.inf
        self._twist_pace = StreamPace()  # the twist samples' period, and when their stream has paused
        self._wheel_pace = StreamPace()  # the same for wheel samples
        self._last_twist_t = -math.inf
        self._fixes_timed = False  # whether the newest fix stated its measurement time
        self._wheels = WheelFeed(TickKinematics(geometry, counts_per_rev), c.predict_period_s)
        # the outputs' carry from the newest anchor: (that anchor, the list index of the first step ending after it,
        # the state at the end of each step since), or None
        self._carried: tuple[Anchor, int, list[State]] | None = None
        self._unsettled: _FixToLearn | None = None  # the last fix, until what it teaches is learnt (settle)
        self._aligner = HeadingAligner(c.heading_align_m, self._offset, enabled=c.heading_align_m > 0.0)
        self._heading_check = HeadingCheck()
        self.counters: dict[str, int] = dict.fromkeys(
            (
                "wheels",
                "twists",
                "odometry_pauses",
                "heading_lost",
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
                "untimed_fixes",
                "calibration_windows",
            ),
            0,
        )
        self._fix_gate = FixGate(c, self.counters, self.modes)
        judged = self._fixes_judged  # by a saved calibration
        if not judged:
            noise = None  # noise learnt before the fixes were judged may be a shared error's agreement
        self._process_noise: ProcessNoiseScale | None = None  # off: the configured noise, and no work per fix
        if c.adaptive_process_noise:
            starts = (1.0, 1.0) if noise is None else (noise.process_noise_scale, noise.heading_noise_scale)
            self._process_noise = ProcessNoiseScale(
                c.process_noise_scale_min,
                c.process_noise_scale_max,
                *starts,
                noise=OdometryNoise(
                    0.5 * (control_noise.lin2 + control_noise.lat2),
                    control_noise.slip2,
                    control_noise.turn2,
                    control_noise.spin2,
                ),
            )
            self._use_noise_scales(self._process_noise)
        if judged:
            self._fix_gate.trust_quieter_fixes(calibration.persistent_fix_var)
            if noise is not None:
                self._fix_gate.start_noise(noise.ips_var)

    # --- inputs -----------------------------------------------------------------------------------

    def on_wheels(self, t: float, ticks: tuple[int, int, int, int]) -> None:
        """Cumulative encoder counts (FL FR RL RR) at time t."""
        self.settle()
        wheels = self._wheels
        if not wheels.accepts(t):
            self.counters["dropped_out_of_order" if math.isfinite(t) else "dropped_non_finite"] += 1
            return
        self.counters["wheels"] += 1
        before_t = wheels.last_t
        gap, pace = t - before_t, self._wheel_pace
        paused = pace.paused_by(gap, wheels.period)
        held = self._pending() if paused else None  # the twist in force when the stream went quiet
        if not paused:
            self._predictor.stale_after_s = pace.pause_after_s
        step = wheels.sample(t, ticks)
        if step is None:
            return
        # a source at rest publishes only on an edge or a keep-alive: a quiet robot at rest is no news (as for twists)
        if held is None or held == (0.0, 0.0, 0.0):
            self._step_to(step[0], step[1], step[1])
            return
        # a pause while moving: the ticks measure the gap's displacement and turn, but not the path between (one arc
        # is a guess)
        self.counters["odometry_pauses"] += 1
        bridge = pace.bridge(gap)
        self._step_to(step[0], step[1], step[1], (ACCEL_DENSITY * bridge, 0.0))
        self._after_pause(before_t)

    def on_twist(self, t: float, vx: float, vy: float, wz: float) -> None:
        """A measured body twist (m/s, rad/s) at time t, held until the next one."""
        self.settle()
        if not (math.isfinite(t) and math.isfinite(vx) and math.isfinite(vy) and math.isfinite(wz)):
            self.counters["dropped_non_finite"] += 1
            return
        if self._track.t and t < self._track.t[-1]:
            self.counters["dropped_out_of_order"] += 1
            return
        self.counters["twists"] += 1
        gap, pace = t - self._last_twist_t, self._twist_pace
        paused = pace.paused_by(gap)
        if not paused:
            self._predictor.stale_after_s = pace.pause_after_s
        self._last_twist_t = t
        track = self._track
        if not len(track):
            self._step_to(t, (vx, vy, wz), (vx, vy, wz))
            return
        held = (track.hx[-1], track.hy[-1], track.hw[-1])
        # each twist is a sample of the velocity at its time: the motion since the previous sample is their mean
        # (the trapezoid rule; holding the older sample would lag the motion by half a sample period)
        step_u = (0.5 * (held[0] + vx), 0.5 * (held[1] + vy), 0.5 * (held[2] + wz))
        if not paused:
            self._step_to(t, step_u, (vx, vy, wz))
            return
        # a pause in the stream: the twist held until the last period, the mean of the samples either side over it (a
        # stream that publishes only changes is then exact). A robot at rest when the stream went quiet most likely
        # stayed so (quiet because nothing changed); one that was moving leaves the motion in the gap a guess, as
        # uncertain as a velocity pinned at both ends may wander (a dropped connection, a stalled recorder)
        if held == (0.0, 0.0, 0.0):
            self._step_to(t - pace.interval_s, held, held)
            self._step_to(t, step_u, (vx, vy, wz))
            return
        self.counters["odometry_pauses"] += 1
        bridge = pace.bridge(gap)
        turn_var = ANGULAR_ACCEL_DENSITY * bridge
        self._step_to(t - pace.interval_s, held, held, (ACCEL_DENSITY * bridge, turn_var))
        self._step_to(t, step_u, (vx, vy, wz))
        self._after_pause(t - gap)
        self._maybe_lose_heading(turn_var)

    def _maybe_lose_heading(self, turn_var: float) -> None:
        """After odometry that does not say how far the robot turned (turn_var rad^2): beyond what a linearised filter
        can carry, the heading is unknown again (as after a recovery) and comes from the fixes, which the position
        follows meanwhile."""
        if self.modes.heading_known and turn_var > self.config.unknown_heading_sigma_rad**2:
            self.modes.lose_heading()
            self.counters["heading_lost"] += 1
            self._predictor.provisional = NO_PROVISIONAL_HEADING
            self._carried = None

    def _after_pause(self, start: float) -> None:
        """After a pause in the odometry that began at `start` while the robot moved: the anchors since made again on
        the steps now known, and the heading window started afresh (its track through the gap is a guess)."""
        self._remake_after(start)
        self._restart_window()
        self._heading_check.suspect = None

    def on_fix_lost(self, t: float) -> None:  # noqa: ARG002 - the daemon's interface carries the time
        """A position packet flagged "coordinates unavailable": never fused, only counted."""
        self.counters["fixes_lost"] += 1

    def _set_clock(self, t: float) -> None:
        """The first input or fix sets the clock: the initial state is at t."""
        first = self._history.anchors[0]
        self._history.reset(first._replace(t=t))

    def _step_to(self, t: float, step_u: Twist3, held: Twist3, gap_var: tuple[float, float] = (0.0, 0.0)) -> None:
        """A step ending at t with twist step_u, then `held` in force (the first input starts the track); gap_var:
        the variance of the step's motion that step_u does not describe (robotd.estimation.track)."""
        track, history = self._track, self._history
        if not len(track):
            start = min(t, history.start) if history.start > -math.inf else t
            track.start(start, held if start == t else (0.0, 0.0, 0.0))
            if history.start == -math.inf:
                self._set_clock(start)
            if start < t:
                # fixes came before any odometry: how the robot moved until now is not known (robotd.estimation.history)
                unknown = (NO_ODOMETRY_SPEED_VAR * (t - start), NO_ODOMETRY_TURN_VAR * (t - start))
                track.append(t, (0.0, 0.0, 0.0), held, unknown)
                self._after_pause(start)
                self._maybe_lose_heading(unknown[1])
        elif t > track.t[-1]:
            if self._calibrator is not None and not gap_var[0]:  # a guessed step ends the window (a gap in its steps)
                self._calibrator.on_step(track.t[-1], t, step_u)
            track.append(t, step_u, held, gap_var)
        else:
            track.hold(held)
        if len(track) - TRIM_STEPS > 2 * TRIM_STEPS:
            self._trim(t)

    def _trim(self, now: float) -> None:
        """Forget the anchors and steps older than the history keeps (history_s before `now`)."""
        needed = self._history.trim(now, self._pending)
        if needed > TRIM_STEPS:
            self._track.drop_before(needed)
            self._carried = None  # its step index moved

    def _pending(self) -> Twist3:
        """The twist beyond the newest step: that of the samples fed since (their mean), or the one in force."""
        u = self._wheels.pending()
        if u is not None:
            return u
        track = self._track
        if not track.t:
            return (0.0, 0.0, 0.0)
        return track.hx[-1], track.hy[-1], track.hw[-1]

    # --- fixes ------------------------------------------------------------------------------------

    def on_fix(self, t: float, x: float, y: float, t_meas: float) -> Diagnostics | None:
        """An IPS fix of the beacon (m) that arrived at t and was measured at t_meas; returns its record. What the
        filter learns from it waits for `settle` (the next input's, or the caller's)."""
        self.settle()
        counters = self.counters
        counters["fixes"] += 1
        if not (isfinite(t) and isfinite(x) and isfinite(y)):
            counters["dropped_non_finite"] += 1
            return None
        timed = isfinite(t_meas)  # a fix without a measurement time (NaN) is stated at its arrival
        stated = t_meas if timed else t
        self._fixes_timed = timed
        if not timed:
            counters["untimed_fixes"] += 1
        if not self.config.latency_compensation or t_meas > t:
            t_meas = t
        elif not timed:
            t_meas = t - self._calibration.latency_s  # the learnt delay
        else:
            t_meas = min(t_meas - self.clock_offset_s, t)  # where the time check puts it on the odometry's clock
        history, track = self._history, self._track
        if history.times[0] == -math.inf:
            self._set_clock(t_meas)
        newest_step = track.t[-1] if track.t else -math.inf
        gate = self._fix_gate
        if t_meas < history.times[0] or (
            self.config.latency_compensation and t_meas < newest_step - self.config.history_s
        ):
            counters["fixes_too_old"] += 1
            nan = math.nan
            return Diagnostics(
                t, t_meas, (nan, nan), (nan, nan, nan), nan, gate.gate, Verdict.TOO_OLD, math.sqrt(gate.r)
            )
        anchors = history.anchors
        k = bisect.bisect_right(history.times, t_meas) - 1
        if t_meas < newest_step or k < len(anchors) - 1:
            counters["late_fixes"] += 1
        prior = self._state_at(anchors[k], t_meas)
        px, py, pth, pp, psens = prior
        r = gate.r
        if not timed and self.config.latency_compensation:
            # the delay is known only to within its sigma: the fix's noise along the motion grows by speed x that
            kx, ky, _ = self._predictor.scale
            u = track.twist_at(t_meas) or self._pending()
            r += (self._calibration.sigmas[3] ** 2) * ((kx * u[0]) ** 2 + (ky * u[1]) ** 2)
        # correlated fixes are fused for what they are worth: each one's variance grows by the AR(1) discount
        r /= self._calibration.fix_information
        ox, oy = self._fused_offset
        inn = ekf.innovation(px, py, pth, pp, x, y, r, ox, oy)
        # a prediction across a pause in the odometry is a worst case, not a variance the innovation can be set
        # against: the noise learnt from it would go to its floor. One along a heading not known is wider than the
        # truth too, but the fixes can still show that they are noisier than assumed: the noise may rise, not fall
        # (falling, it took the libRSF robot's 3 cm IPS to 1.7 cm by the first window's re-alignment)
        travel = Travel(*track.travel_at(t_meas))  # for the gate with the heading unknown, and the process noise
        verdict = gate.judge(
            t_meas, inn, r, learn=not self._paused_at(t_meas), lower=self.modes.heading_known, travelled=travel.distance
        )
        before = self.modes.on_verdict(verdict)
        aligner = self._aligner
        if aligner.enabled and self.modes.placed:
            if before is PositionMode.INITIALISING:
                # the first window starts with the fix that placed the position: at its measurement time, which is
                # before the newest step (a window begun there left the fix out, and a 2 Hz beacon's robot drove half
                # a second more without a heading)
                self._restart_window(t_meas)
            # with the heading unknown the gate allows for the motion since the last fix in any direction (Predictor):
            # a fix beyond it is one that no heading explains, an echo. In the window it would count against every
            # rotation, and a burst of them (a third of the window's points) left it no heading at all while the
            # robot drove on. With the heading known the window must see such fixes: a heading gone wrong is what
            # makes good fixes look far
            if verdict is not Verdict.GATED or self.modes.heading_known:
                aligner.record(x, y, t_meas, track.pose_at(t_meas))
        if verdict is Verdict.ACCEPTED:
            anchor = self._fuse(prior, t_meas, (x, y, r), inn)
        elif verdict is Verdict.SEEDED or verdict is Verdict.RECOVERED:
            anchor = self._seed(prior, t_meas, (x, y, r), verdict)
        else:
            anchor = Anchor(t_meas, px, py, pth, pp, FixRecord(x, y, r, fused=False), psens)
        history.place(k, anchor, self._remake, self._pending)  # every later anchor again, from the corrected state
        if len(history.times) > TRIM_ANCHORS:
            self._trim(t_meas)
        if verdict is Verdict.ACCEPTED or verdict is Verdict.SEEDED or verdict is Verdict.RECOVERED:
            self._last_accept_t = max(self._last_accept_t, t_meas)
        self._unsettled = _FixToLearn(verdict, t_meas, inn, r, prior, anchor, stated, x, y, timed, travel)
        return Diagnostics(
            t, t_meas, (inn.nu_x, inn.nu_y), (inn.s_xx, inn.s_xy, inn.s_yy), inn.nis, gate.gate, verdict, math.sqrt(r)
        )

    def settle(self) -> None:
        """Learn from the last fix: the process noise, the calibration, the heading's re-alignment (a window's fit
        can take milliseconds). `on_fix` leaves this to the next input, which settles first, or to the caller, so
        that the fix's pose can be published before (the daemon); the numbers are the same either way."""
        fix, self._unsettled = self._unsettled, None
        if fix is None:
            return
        if self._process_noise is not None:
            self._learn_process_noise(self._process_noise, fix)
        if fix.verdict is Verdict.ACCEPTED and self._calibrator is not None:
            self._calibrate(fix.stated, fix.x, fix.y, timed=fix.timed)
        aligner, track = self._aligner, self._track
        if aligner.enabled and track.t and track.dist[-1] >= aligner.next_fit:
            self._maybe_realign()
        if not self.modes.heading_known and self.modes.placed:
            self._provisional_heading()
        # an output taken before this (the fix's own pose) carried the state with the noise and scales then in use
        self._carried = None

    def _learn_process_noise(self, scale: ProcessNoiseScale, fix: _FixToLearn) -> None:
        """Give an accepted fix's innovation, with the state before it and the anchor it left, to the process noise
        scales (any other verdict restarts their shadows); use the scales when they moved."""
        if fix.verdict is not Verdict.ACCEPTED:
            scale.forget()
            return
        calibration = self._calibration
        # fix errors that persist look like odometry drift to every shadow: learn only from fixes judged independent,
        # by a window or, before the first one closes, by a heading fit, and drop what was learnt from fixes judged
        # correlated after all (a heading fit's few residuals can miss what a window finds; meanwhile persistent
        # errors could only have raised the scale). Waiting for the first window left the start, a quarter of a
        # one-minute run, on the configured noise
        if calibration.fix_correlation > 0.0 and scale.reset():
            self._use_noise_scales(scale)
        independent = self._fixes_judged and calibration.fix_correlation == 0.0
        learn = independent and self.modes.heading_known
        (px, py, pth, pp, _), anchor = fix.prior, fix.anchor
        prior, posterior = Pose(px, py, pth, pp), Pose(anchor.x, anchor.y, anchor.theta, anchor.p)
        freeze = self._heading_frozen(fix.t_meas)
        if scale.on_fix(fix.t_meas, fix.inn, fix.r, prior, posterior, fix.travel, learn=learn, freeze_heading=freeze):
            self._use_noise_scales(scale)

    def _use_noise_scales(self, scale: ProcessNoiseScale) -> None:
        """Predict with the configured odometry noise times the learnt scales (and give the calibration that noise)."""
        self._predictor.scale_noise(scale.value, scale.heading_value)
        self._noise_to_calibrator()

    def _noise_to_calibrator(self) -> None:
        """The odometry noise in use, which the calibration's windows allow for."""
        if self._calibrator is not None:
            n = self._predictor.noise
            self._calibrator.odometry_noise = (n.lin2, n.lat2, n.slip2, n.turn2)

    @property
    def _fixes_judged(self) -> bool:
        """Whether the fixes' correlation is known: a calibration window (this run's or a saved one's) or, before
        the first, a heading fit has judged them (robotd.estimation.calibration.Calibrator.judged)."""
        return self._calibrator is not None and self._calibrator.judged

    @property
    def learnt_noise(self) -> LearntNoise:
        """The IPS noise variance and the process noise scales in use, for the next start."""
        return LearntNoise(self._fix_gate.r, self.process_noise_scale, self.heading_noise_scale)

    @property
    def process_noise_scale(self) -> float:
        """The factor on the configured odometry position noise variances in use (1 until learnt, and when not
        learnt)."""
        return 1.0 if self._process_noise is None else self._process_noise.value

    @property
    def heading_noise_scale(self) -> float:
        """The factor on the configured odometry heading noise variances in use (1 until learnt, and when not
        learnt)."""
        return 1.0 if self._process_noise is None else self._process_noise.heading_value

    def _calibrate(self, stated: float, x: float, y: float, *, timed: bool) -> None:
        """Give an accepted fix to the calibration; take its new values when a window's fit changed them."""
        calibrator = self._calibrator
        if calibrator is None or not calibrator.on_fix(stated, x, y, timed=timed):
            return
        windows = self._calibration.windows
        calibration = self._calibration = calibrator.current
        self.counters["calibration_windows"] += calibration.windows - windows
        self._fix_gate.trust_quieter_fixes(calibration.persistent_fix_var)
        self._use_scales(calibration)
        self._carried = None  # states carried with the old scales

    def _use_scales(self, calibration: Calibration) -> None:
        """Predict with the calibration's odometry scales and, while it learns them, their uncertainty."""
        kx, ky, kw = calibration.kx, calibration.ky, calibration.kw
        self._predictor.scale = (kx, ky, kw)
        if self._calibrator is not None:
            sx, sy, sw = calibration.sigmas[:3]
            old, new = self._predictor.scale_var, ((sx / kx) ** 2, (sy / ky) ** 2, (sw / kw) ** 2)
            self._predictor.scale_var = new
            self._history.rescale_sensitivity(old, new)

    @property
    def clock_offset_s(self) -> float:
        """How far fixes' stated measurement times run ahead of the odometry's clock, when the time check finds it
        beyond twice its own sigma (0 until then, and without stated times).

        Odometry stamps follow the source's convention (a twist stamped at the start, middle or end of the interval
        it averages; a driver's pipeline), which no log states: a timed fix is placed where the check puts it on the
        odometry's track, as an untimed one is placed by its learnt delay.
        """
        calibration = self._calibration
        error = calibration.time_error_s
        return error if calibration.windows and abs(error) > 2.0 * calibration.sigmas[TAU_K] else 0.0

    @property
    def time_sigma_s(self) -> float:
        """How uncertain an estimate's time is on the fixes' clock (s), given as uncertainty along the motion in its
        covariance: a twist stream's stamp convention (STAMP_CONVENTION_VAR) until timed fixes have been checked
        against the odometry (clock_offset_s); 0 for wheel ticks (counts are read at their time) and for the
        filters that calibrate nothing.

        Without stated times the fixes' delay is learnt against the odometry's clock, so it absorbs the stamps'
        offset (the two are one unknown) and every estimate sits on the odometry's clock, up to half a period off.
        """
        if self._calibrator is None or (self._fixes_timed and self._calibration.windows):
            return 0.0
        return self._twist_pace.interval_s * math.sqrt(STAMP_CONVENTION_VAR)

    @property
    def calibration(self) -> Calibration:
        """The odometry scales and fix delays in use, with their uncertainty."""
        return self._calibration

    def _paused_at(self, t: float) -> bool:
        """Whether the odometry at t is a guess: before any, within a pause's step, or past the newest step with the
        held twist gone stale (robotd.estimation.history.History.stale)."""
        track = self._track
        if not track.t:
            return True
        if t > track.t[-1]:
            return self._history.stale(t, self._pending())
        return bool(track.gap_var[bisect.bisect_left(track.t, t)])

    def _remake_after(self, t: float) -> None:
        """Make the anchors after t again on the steps now known (fixes fused during a pause in the odometry met a
        state extrapolated with the twist held before it)."""
        history = self._history
        k = bisect.bisect_right(history.times, t) - 1
        if 0 <= k < len(history.anchors) - 1:
            first = history.anchors[k + 1]
            state = history.state_at(history.anchors[k], first.t, self._pending)
            history.place(k, self._remake(state, first), self._remake, self._pending)
            self._carried = None

    def _remake(self, state: State, old: Anchor) -> Anchor:
        """An anchor made again at its time from the state there: its fix fused again, its seed moved again."""
        fix = old.fix
        x, y, th, p, sens = state
        if fix is None:
            return Anchor(old.t, x, y, th, p, None, sens)
        if fix.fused:
            inn = ekf.innovation(x, y, th, p, fix.zx, fix.zy, fix.r, *self._fused_offset)
            return self._fuse(state, old.t, (fix.zx, fix.zy, fix.r), inn)
        if fix.seed is not None:
            return _seeded(old.t, state, fix, fix.seed)
        return Anchor(old.t, x, y, th, p, fix, sens)

    def _fuse(self, prior: State, t: float, z: tuple[float, float, float], inn: ekf.Innovation) -> Anchor:
        """The anchor of fix z = (zx, zy, r) fused at t into the prior."""
        k = ekf.gain(prior[3], inn, freeze_heading=self._heading_frozen(t))
        x, y, th, p = ekf.apply_gain(prior[0], prior[1], prior[2], prior[3], inn, z[2], k)
        sens = ekf.corrected_sensitivity(prior[4], inn, k)
        return Anchor(t, x, y, th, p, FixRecord(z[0], z[1], z[2], fused=True), sens)

    @property
    def _fused_offset(self) -> tuple[float, float]:
        """The beacon's lever arm as fixes are fused (robot frame): while the heading is unknown, its expected value.

        The heading the filter then carries is a placeholder: through it the lever arm would put the centre up to
        twice its length off, on every fix alike. For a heading known to within sigma (the provisional heading that
        the fixes so far give: robotd.estimation.history.Predictor) the expected lever arm is exp(-sigma^2 / 2) of
        it, turned by the provisional correction; with none, the centre is anywhere on a circle around the beacon and
        the filter follows the circle's centre, the beacon. What is left of the lever arm's uncertainty is in P
        (_extrapolate); the window that finds the heading places the centre (_realign, with the whole lever arm).
        """
        ox, oy = self._offset
        if self.modes.heading_known:
            return ox, oy
        shrink, turn = self._predictor.provisional
        c, s = shrink * math.cos(turn), shrink * math.sin(turn)
        return c * ox - s * oy, s * ox + c * oy

    def _lever_arm_var(self) -> float:
        """The variance per axis of the lever arm's part of the position, with the heading unknown (the caller asks
        only then): of a vector of length |o| at a heading known to within sigma, |o|^2 (1 - exp(-sigma^2)) / 2."""
        shrink = self._predictor.provisional[0]
        return 0.5 * (self._offset[0] ** 2 + self._offset[1] ** 2) * (1.0 - shrink * shrink)

    def _heading_frozen(self, t: float) -> bool:
        """Whether a fix at t leaves the heading as it is: at rest a fix says nothing about the heading; with the
        heading unknown the model has no heading to correct."""
        if not self.modes.heading_known:
            return True
        u = self._track.twist_at(t) or self._pending()
        return math.hypot(u[0], u[1]) < self.config.heading_min_speed_mps

    def _seed(self, prior: State, t: float, z: tuple[float, float, float], verdict: Verdict) -> Anchor:
        """Move the beacon onto the agreeing fixes (their median innovation), forgetting the position's past."""
        if verdict is Verdict.RECOVERED:
            self._restart_window()  # carried robots may have been turned too (modes: the heading is unknown again)
            self._heading_check.suspect = None
        shift = self._fix_gate.seed_shift(verdict)
        zx, zy, r = z
        return _seeded(t, prior, FixRecord(zx, zy, r, fused=False, seed=shift), shift)

    # --- heading alignment --------------------------------------------------------------------------

    def _restart_window(self, at: float | None = None) -> None:
        """Start a new heading window at the newest step, or at time `at` on the track when given (a fix's
        measurement time: the fix is then the window's first)."""
        track = self._track
        if at is not None and (pose := track.pose_at(at)) is not None:
            self._aligner.restart(at, pose, track.travel_at(at)[0])
            return
        t, newest, dist = track.newest(self._history.start)
        self._aligner.restart(t, newest, dist)

    def _maybe_realign(self) -> None:
        """Take the heading of the aligner's rotation fit when the heading modes say so (robotd.estimation.modes)."""
        now_t, now_pose, dist = self._track.newest(self._history.start)
        # an unknown heading is taken from a whole window: the longer the track, the better its direction
        fit = self._aligner.check(self._fix_gate.r, now_t, now_pose, dist, whole=not self.modes.heading_known)
        if fit is None:
            return
        calibrator = self._calibrator
        if calibrator is not None and calibrator.judge_fixes(*fit.fixes):
            # the first judgement of the fixes, a window before the calibration's: fuse them for what they are worth
            self._calibration = calibrator.current
            self._fix_gate.trust_quieter_fixes(self._calibration.persistent_fix_var)
        _, _, theta, p, _ = self._state_at_newest_step()
        evidence = self._heading_check.evidence(fit, theta, p[5], self.modes.heading)
        if evidence is not None and self.modes.on_evidence(evidence):
            self._realign(fit)

    def _provisional_heading(self) -> None:
        """With the heading unknown: move the position along the heading the window's fixes so far give (its rotation
        fit), by the share of the motion that its sigma expects (robotd.estimation.history.Predictor)."""
        aligner = self._aligner
        provisional = NO_PROVISIONAL_HEADING
        fit = aligner.fit_so_far(self._fix_gate.r, PROVISIONAL_MIN_FIXES)
        if fit is not None:
            rotation, sigma, _, _, spread = fit
            # a short track's few residuals understate the noise (the fit absorbs it): not below the IPS noise in use
            sigma *= math.sqrt(max(1.0, self._fix_gate.r / max(spread.variance, 1e-12)))
        if fit is not None and sigma <= PROVISIONAL_MAX_SIGMA_RAD:
            _, now_pose, _ = self._track.newest(self._history.start)
            turned = aligner.in_window(now_pose)[2]  # the odometry's turn since the window began
            theta = self._state_at_newest_step()[2]
            # the filter moves along its guess; the fit says the window began facing `rotation`
            provisional = (math.exp(-0.5 * sigma * sigma), ekf.wrap_angle(rotation - (theta - turned)))
        if provisional != self._predictor.provisional:
            self._predictor.provisional = provisional
            self._carried = None  # states carried with the old provisional heading

    def _realign(self, fit: RotationFit) -> None:
        """Restart the state from the window's fit: its heading, and the position its translation puts it at."""
        ax, ay, ath = fit.window_odo
        sigma = fit.sigma
        self.counters["heading_realigned"] += 1
        c, s = math.cos(fit.rotation), math.sin(fit.rotation)
        x, y = fit.tx + ax * c - ay * s, fit.ty + ax * s + ay * c
        r = self._fix_gate.r
        when = self._track.t[-1] if self._track.t else -math.inf
        anchor = Anchor(when, x, y, ekf.wrap_angle(fit.rotation + ath), (r, 0.0, 0.0, r, 0.0, sigma * sigma), None)
        # the states before now were built on the wrong heading: start again from here
        self._history.reset(anchor)
        self._fix_gate.forget()
        self._restart_window()

    # --- output ---------------------------------------------------------------------------------------

    def _state_at_newest_step(self) -> State:
        """The state at the newest step, or at the newest anchor when that is later (between two fixes the outputs
        carry the previous output's state on, step by step)."""
        history, track = self._history, self._track
        anchor, newest = history.anchors[-1], len(track.t) - 1
        carried = self._carried
        if carried is not None and carried[0] is anchor:
            first, states = carried[1], carried[2]
            last = first + len(states) - 1
            if last < newest:
                return history.carry(states[-1], track.t[last], last + 1, newest, states)
            if last == newest:
                return states[-1]
        if newest < 0 or track.t[newest] <= anchor.t:
            return anchor.state
        first, states = bisect.bisect_right(track.t, anchor.t), []
        self._carried = (anchor, first, states)
        return history.carry(anchor.state, anchor.t, first, newest, states)

    def _state_at(self, anchor: Anchor, t: float) -> State:
        """The state at t carried from anchor (history.state_at): taken up from the outputs' carry when that began at
        the same anchor, whose states are the same moves (a fix's prior, measured before the newest step)."""
        carried = self._carried
        if carried is not None and carried[0] is anchor:
            first, states = carried[1], carried[2]
            steps_t = self._track.t
            j = bisect.bisect_right(steps_t, t, first) - 1
            if first <= j < first + len(states):
                return self._history.move_within(states[j - first], steps_t[j], t, self._pending)
        return self._history.state_at(anchor, t, self._pending)

    def pose(self, t: float | None = None) -> PoseEstimate:
        """The estimate, extrapolated with the twist in force to time t when t is later than the newest input."""
        when, x, y, th, p = self._extrapolate(t)
        vx, vy, wz = self._twist_in_force()
        age = when - self._last_accept_t
        return PoseEstimate(when, x, y, th, vx, vy, wz, ekf.cov_full(p), age, self.modes.position)

    def position(self, t: float) -> tuple[float, float, float, ekf.Cov] | None:
        """x, y, theta and P (upper triangle) of pose(t), or None before a fix placed the position.

        The replay's per-output call: the same numbers as pose(t) without building a PoseEstimate.
        """
        if not self.modes.placed:
            return None
        _, x, y, th, p = self._extrapolate(t)
        return x, y, th, p

    def _twist_in_force(self) -> Twist3:
        """The odometry's twist beyond the newest step, calibrated."""
        raw = self._pending()
        kx, ky, kw = self._predictor.scale
        return raw[0] * kx, raw[1] * ky, raw[2] * kw

    def _extrapolate(self, t: float | None) -> tuple[float, float, float, float, ekf.Cov]:
        """Time, pose and P of the newest state carried forward to t when t is later (one prediction step with the
        twist in force: the mean as eq. 5, P as eq. 7).

        P includes the uncertainty of the estimate's time (time_sigma_s, along the motion), the fixes' correlated
        error (calibration.fix_correlated_var): the filter fuses fixes as if their errors were independent, which
        averages away an error they share; the estimate cannot be surer than that, and while the heading is unknown
        the lever arm's (_fused_offset): every fix shares it.
        """
        # the replay's per-sample path (position): attributes read once, no property or helper not needed
        steps_t, history = self._track.t, self._history
        newest_step = steps_t[-1] if steps_t else -math.inf
        anchor_t = history.anchors[-1].t
        when = max(newest_step, anchor_t)
        state = self._state_at_newest_step()
        if t is None:
            t = max(when, self._wheels.last_t)
        if t > when and math.isfinite(when):
            # the same process model as a step: the covariance grows with the motion the extrapolation assumes
            if steps_t:
                state = history.beyond_newest(state, when, t, self._pending())
            else:
                state = history.move_within(state, when, t, self._pending)
            when = t
        x, y, th, p, _ = state
        tau = self.time_sigma_s if self._twist_pace.interval_s > 0.0 else 0.0  # per output: wheel counts skip the call
        if tau > 0.0:  # an error tau in the estimate's time is an error u * tau in its pose, along the motion
            u = self._twist_in_force()
            c, s = math.cos(th), math.sin(th)
            ux, uy = (c * u[0] - s * u[1]) * tau, (s * u[0] + c * u[1]) * tau
            uw = u[2] * tau
            xx, xy, xt, yy, yt, tt = p
            p = (xx + ux * ux, xy + ux * uy, xt + ux * uw, yy + uy * uy, yt + uy * uw, tt + uw * uw)
        shared = self._calibration.fix_correlated_var
        if not self.modes.heading_known:  # the lever arm's share is known with the heading
            shared += self._lever_arm_var()
        if shared > 0.0:
            p = (p[0] + shared, p[1], p[2], p[3] + shared, p[4], p[5])
        return when, x, y, th, p


def _seeded(t: float, state: State, fix: FixRecord, shift: tuple[float, float]) -> Anchor:
    """The anchor of a re-seed at t: the state moved by `shift` onto the fixes, its position as uncertain as fix.r
    and owing nothing to the odometry (its heading and the heading's sensitivity kept)."""
    x, y, th, p, sens = state
    r = fix.r
    return Anchor(t, x + shift[0], y + shift[1], th, (r, 0.0, 0.0, r, 0.0, p[5]), fix, ekf.heading_sensitivity(sens))


__all__ = ["Diagnostics", "Estimator", "LearntNoise", "PoseEstimate", "PositionMode", "Verdict"]
