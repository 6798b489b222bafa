"""Estimates marked at many output times of a replay, evaluated together with numpy.

An output of a replayed filter is the newest state carried to the output's time: the newest anchor carried to the
newest visible step (robotd.history: through the rest of its step, then robotd.track's closed form), then moved on,
mean only, with the twist of the samples fed since (Estimator.position). A mark keeps what that depends on at the
output's time (the anchor and heading mode, for a run of outputs at wheel samples between two fixes), so that all of
a log's outputs are computed at the end in a few array operations, with the same arithmetic, instead of one by one.
"""

from __future__ import annotations

from typing import Any, cast

import numpy as np
import numpy.typing as npt

from robotd import ekf
from robotd.history import Anchor, widen_for_unknown_heading
from robotd.track import TrackArrays, carry
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
    mid = th + 0.5 * wz * dt
    c, s = np.cos(mid), np.sin(mid)
    moving = dt > 0.0
    x = np.where(moving, x + (vx * c - vy * s) * dt, x)
    y = np.where(moving, y + (vx * s + vy * c) * dt, y)
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


__all__ = ["Columns", "Span", "evaluate"]
