"""Estimates marked at many output times of a replay, evaluated together with numpy.

An output of a replayed filter is the newest state carried to the output's time: the newest anchor carried to the
newest visible step (robotd.history: through the rest of its step, then robotd.track's closed form), then moved on,
mean only, with the twist of the samples fed since (Estimator.position). A mark keeps what that depends on at the
output's time (the anchor and heading mode, for a run of outputs at wheel samples between two fixes), so that all of
a log's outputs are computed at the end in a few array operations, with the same arithmetic, instead of one by one.
"""

from __future__ import annotations

import math
from typing import Any, cast

import numpy as np
import numpy.typing as npt

from robotd import ekf, kinematics
from robotd.config import EkfConfig
from robotd.estimator import Estimator, TrackState
from robotd.history import Anchor, widen_for_unknown_heading
from robotd.track import StepTwists, TrackArrays, carry, displacement
from robotd.wheelsteps import Loaded, TickKinematics

FloatArray = npt.NDArray[np.float64]


Span = tuple[npt.NDArray[np.int64], Anchor, bool]
"""Outputs at some loaded wheel samples (indices), with the newest anchor then and whether the heading was known."""


Columns = tuple[FloatArray, FloatArray, FloatArray, FloatArray, tuple[FloatArray, ...]]
"""t, x, y, theta and P's six upper-triangle entries, one element per output."""


def evaluate(
    spans: list[Span],
    track: TrackArrays,
    loaded: Loaded,
    kinematics: TickKinematics,
    noise: ekf.ControlNoise,
    *,
    midpoint: bool,
) -> Columns:
    """The outputs of the spans, in order (see the module docstring)."""
    if not spans:
        empty = np.zeros(0)
        return empty, empty, empty, empty, (empty,) * 6
    samples = np.concatenate([span[0] for span in spans])
    counts = [len(span[0]) for span in spans]
    t_out = loaded.times[samples]
    at, ax, ay, ath, ap, _ = zip(*(span[1] for span in spans), strict=True)
    a_t = np.repeat(at, counts)
    x, y, th = np.repeat(ax, counts), np.repeat(ay, counts), np.repeat(ath, counts)
    p = tuple(np.repeat(column, counts) for column in zip(*ap, strict=True))
    known = np.repeat([span[2] for span in spans], counts)
    fed = samples + 1
    visible = np.searchsorted(loaded.ends, fed, side="left")
    newest = np.array(visible, dtype=np.int64) - 1
    step_t = track.t[newest]
    # anchors before the newest step: carried to it (the others are the newest state themselves)
    on = np.flatnonzero(step_t > a_t)
    if len(on):
        state = (x[on], y[on], th[on], tuple(c[on] for c in p))
        sx, sy, sth, sp = _carry(state, a_t[on], newest[on], known[on], track, noise, midpoint=midpoint)
        x[on], y[on], th[on] = sx, sy, sth
        for column, values in zip(p, sp, strict=True):
            column[on] = values
    when = np.maximum(step_t, a_t)
    # the twist beyond the newest step: the samples fed since it, or the twist held after it
    last = samples
    end = loaded.ends[newest]
    vx, vy, wz = track.hx[newest].copy(), track.hy[newest].copy(), track.hw[newest].copy()
    since = np.flatnonzero(last > end)
    if len(since):
        counts = loaded.ticks[last[since]] - loaded.ticks[end[since]]
        vx[since], vy[since], wz[since] = kinematics.twists(
            counts, loaded.times[last[since]] - loaded.times[end[since]]
        )
    # moved on to the output's time, mean only (as Estimator._extrapolate)
    dt = np.where(t_out > when, t_out - when, 0.0)
    dx, dy, _, _ = displacement(vx, vy, wz, dt, th, midpoint=True, lib=np)
    moving = dt > 0.0
    x = np.where(moving, x + dx, x)
    y = np.where(moving, y + dy, y)
    th = np.where(moving, (th + wz * dt + np.pi) % ekf.TWO_PI - np.pi, th)  # ekf.wrap_angle
    return t_out, x, y, th, p


def _carry(  # noqa: PLR0917 - the parts of many states, as arrays
    state: Any, a_t: FloatArray, newest: Any, known: Any, track: TrackArrays, noise: ekf.ControlNoise, *, midpoint: bool
) -> Any:
    """States at anchor times a_t carried to steps `newest` (later than a_t): History.state_at, many at once."""
    b = np.searchsorted(track.t, a_t, side="right")  # the first step ending after the anchor
    move = cast(Any, ekf.motion_step(noise, midpoint=midpoint, lib=np))
    vx, vy, wz = track.vx[b], track.vy[b], track.wz[b]
    dt = track.t[b] - a_t
    x, y, th, p = move(*state, vx, vy, wz, dt)
    unknown = ~known
    if unknown.any():
        widened = widen_for_unknown_heading(p, vx, vy, dt)
        p = tuple(np.where(unknown, w, k) for w, k in zip(widened, p, strict=True))
    out_x, out_y, out_th = x.copy(), y.copy(), th.copy()
    out_p = tuple(np.array(c, dtype=np.float64, copy=True) for c in p)
    for mode in (True, False):
        rows = np.flatnonzero(known == mode)
        if not len(rows):
            continue
        bb, j = b[rows], newest[rows]
        carried = carry(
            (x[rows], y[rows], th[rows], tuple(c[rows] for c in p)),
            track.oth[bb],
            (track.ox[j] - track.ox[bb], track.oy[j] - track.oy[bb], track.oth[j] - track.oth[bb]),
            (-track.oy[j], track.ox[j]),
            track.sums[bb].T,
            track.sums[j].T,
            heading_known=mode,
            lib=np,
        )
        out_x[rows], out_y[rows], out_th[rows] = carried[0], carried[1], carried[2]
        for column, values in zip(out_p, carried[3], strict=True):
            column[rows] = values
    return out_x, out_y, out_th, out_p


class ReplayEstimator(Estimator):
    """The estimator of a replay: a whole log's wheel or twist samples may be taken at once, and its outputs marked
    as it goes and computed together at the end (`marked`). Fed one event at a time, it is the daemon's Estimator."""

    def __init__(
        self,
        ekf_config: EkfConfig,
        geometry: kinematics.Geometry,
        ips_offset_m: tuple[float, float],
        counts_per_rev: int,
        *,
        paper: bool = False,
    ) -> None:
        super().__init__(ekf_config, geometry, ips_offset_m, counts_per_rev, paper=paper)
        self._loaded_kind = "wheels"  # what load_wheels or load_twists took
        self._spans: list[Span] = []  # outputs marked at loaded samples (mark_samples)
        self._ready: list[tuple[float, float, float, float, ekf.Cov]] = []  # outputs computed when marked (mark)
        self._arrays: TrackArrays | None = None

    def load_wheels(
        self, times: npt.NDArray[np.float64], ticks: npt.NDArray[np.int64], ends: list[int] | None = None
    ) -> bool:
        """Take a whole log's wheel samples at once (times strictly increasing and finite, ticks n x 4), to be fed
        in order with on_wheel_samples; the steps are those of feeding them one by one. False (nothing taken) when
        inputs were already given or the times are not clean. Twist samples cannot be mixed in afterwards.

        `ends`, if given, is wheelsteps.step_ends(times, predict_period_s), already computed by the caller.
        """
        if len(self._track):
            return False
        steps = self._wheels.load(times, ticks, ends)
        if steps is None:
            return False
        t0 = float(times[0])
        self._track.start(t0, (0.0, 0.0, 0.0))
        self._track.extend(steps)
        if self._history.start == -math.inf:
            self._set_clock(t0)
        self._history.visible = 0
        return True

    def load_twists(
        self,
        times: npt.NDArray[np.float64],
        vx: npt.NDArray[np.float64],
        vy: npt.NDArray[np.float64],
        wz: npt.NDArray[np.float64],
    ) -> bool:
        """Take a whole log's twist samples at once (times strictly increasing, all finite), to be fed in order with
        on_loaded_samples; the steps are those of on_twist one by one. False (nothing taken) otherwise."""
        if len(self._track) or not all(np.all(np.isfinite(column)) for column in (vx, vy, wz)):
            return False
        if not self._wheels.load_steps(times):
            return False
        self._loaded_kind = "twists"
        t0 = float(times[0])
        self._track.start(t0, (float(vx[0]), float(vy[0]), float(wz[0])))
        # a twist is held until the next: the step to sample k moves with twist k - 1
        self._track.extend(StepTwists(times[1:], vx[:-1], vy[:-1], wz[:-1], (vx[1:], vy[1:], wz[1:])))
        if self._history.start == -math.inf:
            self._set_clock(t0)
        self._history.visible = 0
        return True

    def on_loaded_samples(self, start: int, stop: int) -> None:
        """Loaded samples (load_wheels, load_twists) [start, stop) have arrived, in order: their steps are revealed."""
        self._history.visible = self._wheels.feed(start, stop)
        self.counters[self._loaded_kind] += stop - start

    def on_wheel_samples(
        self, times: list[float], ticks: list[tuple[int, int, int, int]], start: int, stop: int
    ) -> None:
        """on_wheels(times[i], ticks[i]) for i in range(start, stop), in one call: the same result.

        After load_wheels, the samples are those loaded, fed in order: their steps are revealed, nothing computed.
        """
        if self._wheels.loaded is None:
            for i in range(start, stop):
                self.on_wheels(times[i], ticks[i])
            return
        self.on_loaded_samples(start, stop)

    def mark(self, t: float) -> None:
        """Take an output at t (that of position(t)), to be read with marked(); none before a fix placed the filter."""
        if self._wheels.loaded is not None:
            raise RuntimeError("after load_wheels outputs are marked at wheel samples: mark_samples")
        if self._fix_gate.state is TrackState.INITIALISING:
            return
        _, x, y, th, _, p = self._extrapolate(t)
        self._ready.append((t, x, y, th, p))

    def mark_samples(self, samples: npt.NDArray[np.int64], *, unplaced: bool = False) -> None:
        """Take outputs at loaded samples (indices, all fed already, none before an earlier mark, no fix since they
        were fed): each that of position(times[i]) right after sample i was fed. Computed by marked(). None before a
        fix placed the filter, unless `unplaced` (odometry alone: the initial pose carried forward)."""
        if self._wheels.loaded is None:
            raise RuntimeError("mark_samples needs samples loaded with load_wheels or load_twists")
        if (self._fix_gate.state is TrackState.INITIALISING and not unplaced) or not len(samples):
            return
        self._spans.append((samples, self._history.newest, self._predictor.heading_known))

    def marked(self) -> tuple[list[float], list[float], list[float], list[float], npt.NDArray[np.float64]]:
        """The outputs marked so far, in order: times, x, y, theta, and P's upper triangles (n x 6)."""
        loaded = self._wheels.loaded
        if loaded is None:
            if not self._ready:
                return [], [], [], [], np.zeros((0, 6))
            t, x, y, th, p = zip(*self._ready, strict=True)
            return list(t), list(x), list(y), list(th), np.array(p, dtype=np.float64)
        if self._arrays is None:
            self._arrays = self._track.arrays()
        t_out, xs, ys, ths, ps = evaluate(
            self._spans, self._arrays, loaded, self._kinematics, self._noise, midpoint=not self.paper
        )
        return t_out.tolist(), xs.tolist(), ys.tolist(), ths.tolist(), np.column_stack(ps)


__all__ = ["Columns", "ReplayEstimator", "Span", "evaluate"]
