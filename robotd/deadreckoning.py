"""Dead reckoning of a whole log at once (numpy): what the Estimator computes from wheel ticks alone, vectorised.

The Estimator integrates accumulated ticks as one step whenever `predict_period_s` has passed since the last step,
at the step's mean twist and midpoint heading; between steps, its pose is the last step's state carried forward at
the pending ticks' mean twist. Without fixes none of that depends on the state, so the step boundaries are found in
one pass over the times, the twists and headings are array operations and the poses cumulative sums. Equal to the
sequential Estimator to rounding (1e-9 over an hour). Applies only to clean inputs (finite, strictly increasing
times); `applies` says so, and the caller falls back to the Estimator otherwise.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from robotd import kinematics
from robotd.track import displacement
from robotd.wheelsteps import TickKinematics, step_ends

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


def applies(t: FloatArray) -> bool:
    """Whether wheel sample times are all finite and strictly increasing (no sample would be dropped)."""
    return bool(np.all(np.isfinite(t)) and np.all(np.diff(t) > 0.0))


def wrap(angle: FloatArray) -> FloatArray:
    """Angles in [-pi, pi)."""
    return np.asarray((angle + math.pi) % (2.0 * math.pi) - math.pi, dtype=np.float64)


def poses_at(  # noqa: PLR0917 - the log's columns and the robot
    t: FloatArray,
    ticks: IntArray,
    record_t: FloatArray,
    record_after: IntArray,
    geometry: kinematics.Geometry,
    counts_per_rev: int,
    period: float,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Poses (x, y, theta) from (0, 0, 0) at times record_t, each taken after the first record_after samples.

    Equal to Estimator.pose(record_t) of an Estimator started at the origin and fed those samples with on_wheels.
    """
    n = len(t)
    ends = np.array(step_ends(t.tolist(), period)[1:], dtype=np.int64)
    starts = np.concatenate(([0], ends[:-1])).astype(np.int64) if len(ends) else np.zeros(0, dtype=np.int64)
    dt = t[ends] - t[starts]
    kinematics = TickKinematics(geometry, counts_per_rev)
    vx, vy, wz = kinematics.twists(ticks[ends] - ticks[starts], dt)
    # entry 0 is the clock set by the first sample, at rest; entry m the state after the m-th step
    dth = wz * dt
    theta = np.concatenate(([0.0], np.cumsum(dth)))
    dx, dy, _, _ = displacement(vx, vy, wz, dt, theta[:-1], midpoint=True, lib=np)
    x = np.concatenate(([0.0], np.cumsum(dx)))
    y = np.concatenate(([0.0], np.cumsum(dy)))
    entry_t = np.concatenate((t[:1], t[ends])) if n else np.zeros(1)
    entry_sample = np.concatenate(([0], ends)).astype(np.int64)
    entry_u = (np.concatenate(([0.0], vx)), np.concatenate(([0.0], vy)), np.concatenate(([0.0], wz)))
    # each record: the newest sample it follows, the newest step entry at or before it, the pending ticks' twist
    newest = record_after - 1
    started = newest >= 0
    newest_c = np.maximum(newest, 0)
    m = np.searchsorted(ends, newest_c, side="right") if len(ends) else np.zeros(len(newest), dtype=np.int64)
    base = entry_sample[m]
    pending = newest_c > base
    pdt = np.where(pending, t[newest_c] - t[base], 1.0) if n else np.ones(len(newest))
    if n:
        pvx, pvy, pwz = kinematics.twists(ticks[newest_c] - ticks[base], pdt)
    else:
        pvx = pvy = pwz = np.zeros(len(newest))
    ux = np.where(pending, pvx, entry_u[0][m])
    uy = np.where(pending, pvy, entry_u[1][m])
    uw = np.where(pending, pwz, entry_u[2][m])
    ex, ey, eth, et = x[m], y[m], theta[m], entry_t[m]
    later = started & (record_t > et)
    h = np.where(later, record_t - et, 0.0)
    hx, hy, _, _ = displacement(ux, uy, uw, h, eth, midpoint=True, lib=np)
    out_x = np.where(later, ex + hx, ex)
    out_y = np.where(later, ey + hy, ey)
    out_th = wrap(np.where(later, eth + uw * h, eth))
    out_x[~started] = 0.0
    out_y[~started] = 0.0
    out_th[~started] = 0.0
    return out_x, out_y, out_th


__all__ = ["applies", "poses_at", "wrap"]
