"""The estimator's short history: the states that fixes left (anchors) on the odometry track, and the state at any
time since the oldest.

An anchor is the state at one instant (a fix's measurement time, or a restart). The state at a later time t is the
newest anchor at or before t carried forward: through the rest of the step it falls in, then across whole steps in
O(1) (robotd.track), then through the part of the step that contains t, or beyond the newest step with the twist in
force. A fix measured in the past is fused at the anchor it makes there; the anchors after it are then made again
from their fixes, so a late fix lands exactly where an on-time one would, at a cost that does not grow with how
late it is. Anchors older than `keep_s` before the newest input are dropped (the newest of them stays: it carries
the state). Pure.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Callable
from typing import Any, NamedTuple

from robotd import ekf
from robotd.track import OdometryTrack, State, unknown_heading_variance

Twist3 = tuple[float, float, float]
SHORT_RUN = 3  # runs of up to this many whole steps are taken one by one (cheaper than the closed form)


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

    @property
    def state(self) -> State:
        """x, y, theta, P."""
        return self.x, self.y, self.theta, self.p


def widen_for_unknown_heading(p: Any, vx: Any, vy: Any, dt: Any) -> Any:
    """P after a step of (vx, vy) for dt with the heading unknown: floats, or arrays of many steps.

    The guessed direction may be off by anything (track.unknown_heading_variance); the position keeps no
    correlation with the heading.
    """
    q = unknown_heading_variance(vx, vy, dt)
    xx, xy, xt, yy, yt, tt = p
    return xx + q, xy, 0.0 * xt, yy + q, 0.0 * yt, tt


class Predictor:
    """Moves a state over part of one step (eqs. 5-7): robotd at the midpoint heading, the paper at the start."""

    def __init__(self, noise: ekf.ControlNoise, *, midpoint: bool) -> None:
        self.noise = noise
        self.midpoint = midpoint
        self._move = ekf.motion_step(noise, midpoint=midpoint)
        # With the heading unknown (power-on anywhere, a robot carried off), odometry says how far the robot went but
        # not in which direction: the state still moves along the guessed heading (right more often than not: robots
        # tend to start facing the map's x axis), but the position's variance grows by the distance squared in every
        # direction and keeps no correlation with the heading, so fixes steer the position freely and the gate does
        # not defend a guess; the heading itself comes from the first whole alignment window.
        self.heading_known = True

    def stepper(self) -> ekf.MotionStep:
        """move() as a function of (x, y, theta, P, vx, vy, wz, dt), for the current heading mode."""
        if self.heading_known:
            return self._move

        def step(  # noqa: PLR0917 - as ekf.motion_step
            x: float, y: float, theta: float, p: ekf.Cov, vx: float, vy: float, wz: float, dt: float
        ) -> State:
            return self.move((x, y, theta, p), (vx, vy, wz), dt)

        return step

    def move(self, state: State, u: Twist3, dt: float) -> State:
        """The state moved by twist u for dt (> 0), with the process noise of that motion."""
        x, y, theta, p = self._move(state[0], state[1], state[2], state[3], u[0], u[1], u[2], dt)
        if self.heading_known:
            return x, y, theta, p
        widened: ekf.Cov = widen_for_unknown_heading(p, u[0], u[1], dt)
        return x, y, theta, widened


class History:
    """Anchors in time order on an odometry track; `visible` steps of the track are known (a replay may load more)."""

    def __init__(self, track: OdometryTrack, predictor: Predictor, first: Anchor, keep_s: float, *, keep_past: bool):
        self.track = track
        self.predictor = predictor
        self.anchors = [first]
        self.times = [first.t]
        self.keep_s = keep_s
        self.keep_past = keep_past
        self.visible = 0  # how many of the track's steps (list indices) are in force

    @property
    def newest(self) -> Anchor:
        """The newest anchor."""
        return self.anchors[-1]

    @property
    def start(self) -> float:
        """The oldest time a fix can be placed at."""
        return self.times[0]

    def reset(self, anchor: Anchor) -> None:
        """Forget the past: the history starts again at anchor."""
        self.anchors = [anchor]
        self.times = [anchor.t]

    def newest_step_t(self) -> float:
        """The end time of the newest visible step (-inf before the clock started)."""
        return self.track.t[self.visible - 1] if self.visible else -math.inf

    def state_at(self, anchor: Anchor, t: float, pending: Callable[[], Twist3]) -> State:
        """The state at t >= anchor.t: anchor carried over the visible steps, then with pending() past the newest."""
        track, vis, step = self.track, self.visible, self.predictor.stepper()
        steps_t = track.t
        x, y, th, p = anchor.state
        at = anchor.t
        i = bisect.bisect_right(steps_t, at, 0, vis) - 1  # the step the anchor falls after
        if i + 1 >= vis:  # nothing known after the anchor: extrapolate
            if t <= at:
                return x, y, th, p
            vx0, vy0, wz0 = pending()
            return step(x, y, th, p, vx0, vy0, wz0, t - at)
        b = i + 1
        vx, vy, wz = track.vx, track.vy, track.wz
        if t <= steps_t[b]:
            return step(x, y, th, p, vx[b], vy[b], wz[b], t - at) if t > at else (x, y, th, p)
        x, y, th, p = step(x, y, th, p, vx[b], vy[b], wz[b], steps_t[b] - at)
        j = bisect.bisect_right(steps_t, t, b, vis) - 1
        if j - b <= SHORT_RUN:
            for k in range(b + 1, j + 1):
                x, y, th, p = step(x, y, th, p, vx[k], vy[k], wz[k], steps_t[k] - steps_t[k - 1])
        else:
            # (with the heading unknown, `step` left no heading correlations: the closed form needs none)
            x, y, th, p = track.across(b, j, (x, y, th, p), heading_known=self.predictor.heading_known)
        if t > steps_t[j]:
            if j + 1 < vis:
                return step(x, y, th, p, vx[j + 1], vy[j + 1], wz[j + 1], t - steps_t[j])
            vx0, vy0, wz0 = pending()
            return step(x, y, th, p, vx0, vy0, wz0, t - steps_t[j])
        return x, y, th, p

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
        if times[0] < horizon - self.keep_s and self.visible:
            # a long outage: carry the base anchor to the newest step before the horizon (what it would be there)
            steps_t = self.track.t
            j = bisect.bisect_right(steps_t, horizon, 0, self.visible) - 1
            if j >= 0 and steps_t[j] > times[0] and (len(times) == 1 or steps_t[j] < times[1]):
                x, y, th, p = self.state_at(anchors[0], steps_t[j], pending)
                anchors[0] = Anchor(steps_t[j], x, y, th, p, None)
                times[0] = steps_t[j]
        return max(bisect.bisect_right(self.track.t, times[0], 0, self.visible) - 1, 0)


__all__ = ["Anchor", "FixRecord", "History", "Predictor", "State", "Twist3", "widen_for_unknown_heading"]
