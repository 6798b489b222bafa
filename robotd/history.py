"""The estimator's short history of states, and the prediction that re-creates it after a late fix.

Each input step and each fix leaves an entry: the state after it and the event that produced it. A fix measured in
the past is fused by rewinding to the last entry before its measurement time; every later entry is then re-created
from its event (`Predictor.step` for inputs), so that a late fix lands exactly where an on-time one would. Entries
older than `keep_s` before the newest are dropped; without latency compensation only the newest is kept. Pure.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Callable
from dataclasses import dataclass

from robotd import ekf

Twist3 = tuple[float, float, float]
TRIM_MIN_ENTRIES = 64  # trimming is amortised: a few dozen entries are cheaper to keep than to cut one by one
UNKNOWN_HEADING_CORRELATION_S = 1.0  # how long a velocity error from an unknown heading is taken to persist


@dataclass(slots=True)
class Entry:
    """The state after one event, and the event (to apply again after a late fix)."""

    t: float
    x: float
    y: float
    theta: float
    p: ekf.Cov
    u: Twist3  # twist in force after t
    step_u: Twist3 | None  # input event: twist used over (previous t, t]; None for a fix
    fix: tuple[float, float, float, bool] | None  # fix event: zx, zy, r, fused


class Predictor:
    """Moves a state forward with a twist (eqs. 5-7): robotd at the midpoint heading, the paper at the start."""

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

    def _moved(self, prev: Entry, u: Twist3, dt: float) -> tuple[float, float, float, ekf.Cov]:
        x, y, theta, p = self._move(prev.x, prev.y, prev.theta, prev.p, u[0], u[1], u[2], dt)
        if self.heading_known:
            return x, y, theta, p
        # the guessed direction may be off by anything: a velocity error of up to twice the speed, correlated over
        # UNKNOWN_HEADING_CORRELATION_S (white noise of that density: no state to carry through re-predictions)
        q = 4.0 * (u[0] * u[0] + u[1] * u[1]) * dt * UNKNOWN_HEADING_CORRELATION_S
        xx, xy, _, yy, _, tt = p
        return x, y, theta, (xx + q, xy, 0.0, yy + q, 0.0, tt)

    def step(self, prev: Entry, t: float, u: Twist3) -> Entry:
        """The state predicted from prev to t with twist u; its `u` is u, it records no event."""
        dt = t - prev.t
        if dt <= 0.0:
            return Entry(t, prev.x, prev.y, prev.theta, prev.p, u, None, None)
        x, y, theta, p = self._moved(prev, u, dt)
        return Entry(t, x, y, theta, p, u, None, None)

    def input_step(self, prev: Entry, t: float, step_u: Twist3, next_u: Twist3) -> Entry:
        """The entry of an input event: the state predicted from prev to t with step_u, next_u in force after t."""
        dt = t - prev.t
        if dt <= 0.0:
            return Entry(t, prev.x, prev.y, prev.theta, prev.p, next_u, step_u, None)
        x, y, theta, p = self._moved(prev, step_u, dt)
        return Entry(t, x, y, theta, p, next_u, step_u, None)


class History:
    """Entries in time order (`times` mirrors their `t` for bisection); the newest is the current state."""

    def __init__(self, first: Entry, keep_s: float, *, keep_past: bool) -> None:
        self.entries = [first]
        self.times = [first.t]
        self.keep_s = keep_s
        self.keep_past = keep_past

    @property
    def last(self) -> Entry:
        """The newest entry: the current state."""
        return self.entries[-1]

    @property
    def start(self) -> float:
        """The time of the oldest entry: fixes measured before it cannot be placed."""
        return self.times[0]

    def set_last_time(self, t: float) -> None:
        """Give the newest entry a time (the first input or fix sets the clock)."""
        self.entries[-1].t = t
        self.times[-1] = t

    def append(self, entry: Entry) -> None:
        """Add the newest entry, dropping entries older than keep_s."""
        self.entries.append(entry)
        self.times.append(entry.t)
        if not self.keep_past:
            del self.entries[:-1], self.times[:-1]
            return
        horizon = entry.t - self.keep_s
        if self.times[0] < horizon and len(self.times) > TRIM_MIN_ENTRIES:
            cut = bisect.bisect_left(self.times, horizon) - 1
            if cut > 0:
                del self.entries[:cut], self.times[:cut]

    def index_at(self, t: float) -> int:
        """The index of the last entry at or before t."""
        return bisect.bisect_right(self.times, t) - 1

    def rewrite(self, k: int, entry: Entry, reapply: Callable[[Entry, Entry], Entry]) -> None:
        """Put entry after index k, then re-create every later entry from its event with reapply(previous, event)."""
        tail = self.entries[k + 1 :]
        del self.entries[k + 1 :], self.times[k + 1 :]
        self.entries.append(entry)
        self.times.append(entry.t)
        prev = entry
        for event in tail:
            prev = reapply(prev, event)
            self.entries.append(prev)
            self.times.append(prev.t)
        if not self.keep_past:
            del self.entries[:-1], self.times[:-1]

    def reset(self, entry: Entry) -> None:
        """Forget the past: the history starts again at entry."""
        self.entries = [entry]
        self.times = [entry.t]


def initial_entry(pose: tuple[float, float, float], p: ekf.Cov) -> Entry:
    """The state before any input: no time yet, at rest."""
    x, y, theta = pose
    return Entry(-math.inf, x, y, ekf.wrap_angle(theta), p, (0.0, 0.0, 0.0), None, None)


__all__ = ["Entry", "History", "Predictor", "Twist3", "initial_entry"]
