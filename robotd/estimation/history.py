"""The estimator's short history: the states that fixes left (anchors) on the odometry track, and the state at any
time since the oldest.

An anchor is the state at one instant (a fix's measurement time, or a restart). The state at a later time t is the
newest anchor at or before t carried forward through the prediction steps (robotd.estimation.track) one by one: through
the rest of the step it falls in, across the whole steps after it, then through the part of the step that contains t, or
beyond the newest step with the twist in force. A fix measured in the past is fused at the anchor it makes there; the
anchors after it are then made again from their fixes, so a late fix lands exactly where an on-time one would.
Anchors older than `keep_s` before the newest input are dropped (the newest of them stays: it carries the state).
Pure.
"""

from __future__ import annotations

import bisect
import dataclasses
import math
from collections.abc import Callable
from typing import NamedTuple

from robotd.estimation import ekf
from robotd.estimation.modes import Modes
from robotd.estimation.track import OdometryTrack, Twist3

State = tuple[float, float, float, ekf.Cov, ekf.Sens]
"""x, y, theta, P (upper triangle) and the pose's sensitivity to the odometry scales (ekf.Sens)."""
UNKNOWN_HEADING_CORRELATION_S = 0.1  # how long a velocity error from an unknown heading persists: a fix interval
NO_PROVISIONAL_HEADING = (0.0, 0.0)  # (shrink, turn): no motion is expected in any direction
# How fast a robot's velocity can drift from the last one sampled, as white acceleration noise: m^2/s^3 (about 0.7
# m/s^2 sustained for a second: a small robot's speed changes by that much) and rad^2/s^3 (1.4 rad/s^2). A twist
# stream that pauses for g leaves the motion between its samples known to within ACCEL_DENSITY g^3 / 12 per axis (the
# integral of a velocity pinned at both ends); one not yet resumed, ACCEL_DENSITY age^3 / 3 (pinned at one end)
ACCEL_DENSITY = 0.5
ANGULAR_ACCEL_DENSITY = 2.0
# Before any odometry (fixes came first) the robot may be moving at a walking pace or turning, unseen: as a velocity
# of that size (0.5 m/s, 1 rad/s per axis) persisting for a fix interval, white noise of density variance x 0.1 s
NO_ODOMETRY_SPEED_VAR = 0.5**2 * UNKNOWN_HEADING_CORRELATION_S  # m^2/s per axis
NO_ODOMETRY_TURN_VAR = 1.0**2 * UNKNOWN_HEADING_CORRELATION_S  # rad^2/s


def blurred(state: State, var_xy: float, var_th: float) -> State:
    """The state with var_xy added to its position's variance per axis and var_th to its heading's."""
    x, y, theta, p, sens = state
    xx, xy, xt, yy, yt, tt = p
    return x, y, theta, (xx + var_xy, xy, xt, yy + var_xy, yt, tt + var_th), sens


class FixRecord(NamedTuple):
    """What a fix did at its anchor, to do again after a later fix was placed before it.

    `fused`: it was fused (fuse it again); otherwise `seed` says where it moved the beacon (a re-seed), or neither
    (it was only recorded). A NamedTuple, as Anchor.
    """

    zx: float
    zy: float
    r: float
    fused: bool
    seed: tuple[float, float] | None = None


class Anchor(NamedTuple):
    """The state at time t, and the fix that left it there (None for a restart or a carried state).

    A NamedTuple: as immutable as a frozen dataclass, and built several times faster (once or twice per fix).
    """

    t: float
    x: float
    y: float
    theta: float
    p: ekf.Cov
    fix: FixRecord | None
    sens: ekf.Sens = ekf.NO_SENS

    @property
    def state(self) -> State:
        """x, y, theta, P, sensitivity."""
        return self.x, self.y, self.theta, self.p, self.sens


class Predictor:
    """Moves a state over part of one step (robotd.estimation.ekf.predict), in the heading mode of
    robotd.estimation.modes.

    With the heading unknown (power-on anywhere, a robot carried off), odometry says how far the robot went but not in
    which direction. Until fixes place the position, the pose is dead reckoning in the start's frame (initial_pose,
    its heading the guess): what a robot without a beacon shows. Once fixes have placed it on the map, the guess is
    worth nothing (a recorded robot rarely starts facing the map's x axis, and moving along a wrong guess is off by up
    to twice the distance): the motion takes the `provisional` heading that the fixes so far give, and its expected
    value for a heading known to within sigma, exp(-sigma^2 / 2) of the displacement; with no such heading yet
    (sigma infinite), the position stays where the fixes put it. Either way its variance grows as for a heading not
    known, in every direction and with no correlation with the heading, so fixes steer the position freely and the
    gate does not defend a guess. The heading itself is taken from the first whole alignment window
    (robotd.estimation.heading).
    """

    def __init__(self, noise: ekf.ControlNoise, modes: Modes, *, midpoint: bool) -> None:
        self.prior_noise = noise  # as configured: the learnt process noise scales multiply its odometry terms
        self.noise = noise
        self.modes = modes
        self.midpoint = midpoint
        self.scale: Twist3 = (1.0, 1.0, 1.0)  # the odometry calibration's multipliers of vx, vy, wz
        self.scale_var: Twist3 = ekf.NO_SCALE_VAR  # their relative variances (see ekf.predict_considering)
        # heading unknown, position placed: (shrink, turn) of the guessed motion, from the fixes so far (see above)
        self.provisional = NO_PROVISIONAL_HEADING
        # how long after the newest step the held twist is no longer the stream's own (a twist stream's next sample
        # is late by then: robotd.estimation.estimator); infinite for wheel counts, whose next sample measures the gap
        self.stale_after_s = math.inf

    def scale_noise(self, position: float, heading: float) -> None:
        """Use the configured odometry noise variances times factors: `position` on the position terms, `heading` on
        the heading's (the paper's per-step terms unchanged)."""
        n = self.prior_noise
        self.noise = dataclasses.replace(
            n,
            lin2=n.lin2 * position,
            lat2=n.lat2 * position,
            spin2=n.spin2 * position,
            slip2=n.slip2 * heading,
            turn2=n.turn2 * heading,
        )

    def move(self, state: State, u: Twist3, dt: float) -> State:
        """The state moved by the odometry twist u (calibrated by `scale`) for dt (> 0), with the process noise of
        that motion."""
        kx, ky, kw = self.scale
        vx, vy, wz = u[0] * kx, u[1] * ky, u[2] * kw
        x, y, theta, p, sens = ekf.predict_considering(
            state[0],
            state[1],
            state[2],
            state[3],
            state[4],
            vx,
            vy,
            wz,
            dt,
            self.noise,
            self.scale_var,
            midpoint=self.midpoint,
        )
        if self.modes.heading_known:
            return x, y, theta, p, sens
        # the velocity error, correlated over about one fix interval (each fix re-anchors the position, so only the
        # motion since the last one is in doubt), as white noise of that density: along a guess, up to twice the
        # speed; placed, the speed in a direction not known (half its square per axis), also along a provisional
        # heading: a short track's fit improves the estimate but is no proof (its residuals are few, its errors may
        # persist), so it does not make the position more certain
        speed2 = vx * vx + vy * vy
        # the position's variance from before the step, not the prediction's: its heading terms grew it across the
        # guessed direction of motion by the distance times the unknown heading's sigma (tens of times the distance's
        # square), and not along it, as if the guess were the likeliest heading
        xx, xy, _, yy, _, _ = state[3]
        tt = p[5]
        if self.modes.placed:
            shrink, turn = self.provisional
            q = speed2 * dt * UNKNOWN_HEADING_CORRELATION_S
            dx, dy = x - state[0], y - state[1]
            c, s = shrink * math.cos(turn), shrink * math.sin(turn)
            x, y = state[0] + c * dx - s * dy, state[1] + s * dx + c * dy
        else:
            q = 4.0 * speed2 * dt * UNKNOWN_HEADING_CORRELATION_S
        return x, y, theta, (xx + q, xy, 0.0, yy + q, 0.0, tt), ekf.heading_sensitivity(sens)


class History:
    """Anchors in time order on an odometry track."""

    def __init__(self, track: OdometryTrack, predictor: Predictor, first: Anchor, keep_s: float, *, keep_past: bool):
        self.track = track
        self.predictor = predictor
        self.anchors = [first]
        self.times = [first.t]
        self.keep_s = keep_s
        self.keep_past = keep_past

    @property
    def newest(self) -> Anchor:
        """The newest anchor."""
        return self.anchors[-1]

    @property
    def start(self) -> float:
        """The oldest time a fix can be placed at."""
        return self.times[0]

    def rescale_sensitivity(self, old: Twist3, new: Twist3) -> None:
        """Every anchor's sensitivity to the odometry scales made fit for their relative variances changed from `old`
        to `new` (ekf.sensitivity_for_scale_var): the states carried from them keep a positive definite P. Nothing
        changes when no variance grew. Most windows grow one (a scale the path does not exercise, as the sideways one
        of a robot that drives only forward, walks on), so it runs about once a window over some hundred anchors: the
        factors are worked out once, and each anchor made whole (NamedTuple._replace took three times as long)."""
        factors = ekf.sensitivity_factors(old, new)
        if factors is None:
            return
        shrink, none = ekf.shrink_sensitivity, ekf.NO_SENS
        self.anchors = [
            a if a.sens is none else Anchor(a.t, a.x, a.y, a.theta, a.p, a.fix, shrink(a.sens, factors))
            for a in self.anchors
        ]

    def reset(self, anchor: Anchor) -> None:
        """Forget the past: the history starts again at anchor."""
        self.anchors = [anchor]
        self.times = [anchor.t]

    def state_at(self, anchor: Anchor, t: float, pending: Callable[[], Twist3]) -> State:
        """The state at t >= anchor.t: anchor carried over the steps, then with pending() past the newest."""
        state, at = anchor.state, anchor.t
        steps_t = self.track.t
        b = bisect.bisect_right(steps_t, at)  # the first step ending after the anchor
        j = bisect.bisect_right(steps_t, t, b) - 1  # the last step ending at or before t
        if j >= b:
            state = self.carry(state, at, b, j)
            at = steps_t[j]
        return self.move_within(state, at, t, pending)

    def carry(self, state: State, at: float, b: int, j: int, into: list[State] | None = None) -> State:
        """The state at `at` (within step b, or at its start) carried to the end of step j >= b; the state at the end
        of each step appended to `into` when given."""
        track, move = self.track, self.predictor.move
        vx, vy, wz, steps_t, gap_var = track.vx, track.vy, track.wz, track.t, track.gap_var
        states = [] if into is None else into
        if steps_t[b] > at:
            state = move(state, (vx[b], vy[b], wz[b]), steps_t[b] - at)
            if gap_var[b]:
                state = self._blurred(state, b, (steps_t[b] - at) / (steps_t[b] - steps_t[b - 1]))
        states.append(state)
        for k in range(b + 1, j + 1):
            state = move(state, (vx[k], vy[k], wz[k]), steps_t[k] - steps_t[k - 1])
            if gap_var[k]:
                state = self._blurred(state, k, 1.0)
            states.append(state)
        return state

    def _blurred(self, state: State, k: int, share: float) -> State:
        """The state with `share` of step k's undescribed motion's variance added (a gap in a twist stream)."""
        track = self.track
        return blurred(state, share * track.gap_var[k], share * track.gap_var_th[k])

    def move_within(self, state: State, at: float, t: float, pending: Callable[[], Twist3]) -> State:
        """The state at `at` moved on to t >= at, within the step that contains t (pending() beyond the newest)."""
        if t <= at:
            return state
        track = self.track
        if not track.t:  # no odometry yet: the motion since `at` is not known
            moved = self.predictor.move(state, pending(), t - at)
            return blurred(moved, NO_ODOMETRY_SPEED_VAR * (t - at), NO_ODOMETRY_TURN_VAR * (t - at))
        k = bisect.bisect_left(track.t, t)
        if k < len(track):
            moved = self.predictor.move(state, (track.vx[k], track.vy[k], track.wz[k]), t - at)
            if track.gap_var[k] and k > 0:
                moved = self._blurred(moved, k, (t - at) / (track.t[k] - track.t[k - 1]))
            return moved
        return self.beyond_newest(state, at, t, pending())

    def stale(self, t: float, u: Twist3) -> bool:
        """Whether the twist u, held since the newest step, is a guess at t: the stream's next sample is overdue and the
        robot was moving (one at rest when the stream went quiet most likely stays so: a stream may publish only
        changes, an encoder source at rest only an edge or a keep-alive)."""
        return t - self.track.t[-1] > self.predictor.stale_after_s and u != (0.0, 0.0, 0.0)

    def beyond_newest(self, state: State, at: float, t: float, u: Twist3) -> State:
        """The state at `at` (at or past the newest step) moved on to t with the twist u held since that step."""
        predictor = self.predictor
        moved = predictor.move(state, u, t - at)
        if t - self.track.t[-1] > predictor.stale_after_s and u != (0.0, 0.0, 0.0):  # stale(t, u), the hot path
            # past the stream's next sample, the held twist is a guess that ages: add what its age adds since `at`
            stale_after, newest = self.predictor.stale_after_s, self.track.t[-1]
            age0, age1 = max(at - newest - stale_after, 0.0), t - newest - stale_after
            grown = (age1**3 - age0**3) / 3.0
            moved = blurred(moved, ACCEL_DENSITY * grown, ANGULAR_ACCEL_DENSITY * grown)
        return moved

    def place(
        self, k: int, anchor: Anchor, remake: Callable[[State, Anchor], Anchor], pending: Callable[[], Twist3]
    ) -> None:
        """Put anchor after index k, then make every later anchor again from its fix with remake(state there, it)."""
        later = self.anchors[k + 1 :]
        del self.anchors[k + 1 :], self.times[k + 1 :]
        self.anchors.append(anchor)
        self.times.append(anchor.t)
        for old in later:
            made = remake(self.state_at(self.anchors[-1], old.t, pending), old)
            self.anchors.append(made)
            self.times.append(made.t)
        if not self.keep_past:
            del self.anchors[:-1], self.times[:-1]

    def trim(self, now: float, pending: Callable[[], Twist3]) -> int:
        """Drop anchors older than keep_s before now (keeping the newest of them), and carry a lone old anchor forward
        so that the steps behind it can go; returns the first step (list index) still needed."""
        horizon = now - self.keep_s
        anchors, times = self.anchors, self.times
        if len(times) > 1 and times[1] <= horizon:
            cut = bisect.bisect_right(times, horizon) - 1
            del anchors[:cut], times[:cut]
        steps_t = self.track.t
        if times[0] < horizon - self.keep_s and steps_t:
            # a long outage: carry the base anchor to the newest step before the horizon (what it would be there)
            j = bisect.bisect_right(steps_t, horizon) - 1
            if j >= 0 and steps_t[j] > times[0] and (len(times) == 1 or steps_t[j] < times[1]):
                x, y, th, p, sens = self.state_at(anchors[0], steps_t[j], pending)
                anchors[0] = Anchor(steps_t[j], x, y, th, p, None, sens)
                times[0] = steps_t[j]
        return max(bisect.bisect_right(steps_t, times[0]) - 1, 0)


__all__ = [
    "ACCEL_DENSITY",
    "ANGULAR_ACCEL_DENSITY",
    "NO_ODOMETRY_SPEED_VAR",
    "NO_ODOMETRY_TURN_VAR",
    "Anchor",
    "FixRecord",
    "History",
    "Predictor",
    "State",
    "blurred",
]
