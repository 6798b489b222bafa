"""The odometry track's closed form, the anchors' history, and the trimmed daemon-mode estimator."""

from __future__ import annotations

import dataclasses
import math
import random

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from robotd import ekf, kinematics
from robotd.config import EkfConfig
from robotd.estimator import Estimator
from robotd.fixgate import FixGate
from robotd.history import Predictor
from robotd.track import OdometryTrack, State, StepTwists

GEOMETRY = kinematics.Geometry()
CPR = 6800
NOISE = ekf.ControlNoise(lin2=4e-4, lat2=9e-4, slip2=2.5e-3, turn2=2.5e-3)
PAPER_NOISE = ekf.ControlNoise(const_v2=0.01, const_w2=0.04)


def _random_track(
    rng: random.Random, n: int, noise: ekf.ControlNoise, *, midpoint: bool, start_x: float
) -> OdometryTrack:
    track = OdometryTrack(noise, midpoint=midpoint)
    track.start(0.0, (0.0, 0.0, 0.0))
    t = np.cumsum([rng.uniform(0.01, 0.2) for _ in range(n)])
    vx = np.array([rng.uniform(-0.6, 0.6) for _ in range(n)])
    vy = np.array([rng.uniform(-0.4, 0.4) for _ in range(n)])
    wz = np.array([rng.uniform(-2.0, 2.0) for _ in range(n)])
    # in two batches: extending a track continues its totals
    half = n // 2
    for part in (slice(0, half), slice(half, n)):
        track.extend(StepTwists(t[part], vx[part], vy[part], wz[part], (vx[part], vy[part], wz[part])))
    # a track far from its origin (the totals' rounding grows with the distance squared)
    track.ox = [x + start_x for x in track.ox]
    track.sums = _recentred(track, start_x)
    return track


def _recentred(track: OdometryTrack, shift: float) -> list[list[float]]:
    """The running totals after moving every odometry position by +shift in x (w = perp(o) moves by +shift in y)."""
    out = []
    for row in track.sums:
        c, s1x, s1y, s2xx, s2xy, s2yy, *rest = row
        out.append(
            [c, s1x, s1y + c * shift, s2xx, s2xy + s1x * shift, s2yy + 2 * s1y * shift + c * shift * shift, *rest]
        )
    return out


def _stepwise(track: OdometryTrack, b: int, j: int, state: State, predictor: Predictor) -> State:
    x, y, th, p = state
    for k in range(b + 1, j + 1):
        x, y, th, p = predictor.move(
            (x, y, th, p), (track.vx[k], track.vy[k], track.wz[k]), track.t[k] - track.t[k - 1]
        )
    return x, y, th, p


@settings(max_examples=40, deadline=None)
@given(
    st.integers(0, 10_000),
    st.sampled_from([(NOISE, True), (PAPER_NOISE, False)]),
    st.booleans(),
    st.sampled_from([0.0, 300.0]),
)
def test_the_closed_form_equals_stepping_across_the_same_steps(
    seed: int, noise_and_rule: tuple[ekf.ControlNoise, bool], heading_known: bool, start_x: float
) -> None:
    noise, midpoint = noise_and_rule
    rng = random.Random(seed)
    track = _random_track(rng, 60, noise, midpoint=midpoint, start_x=start_x)
    predictor = Predictor(noise, midpoint=midpoint)
    predictor.heading_known = heading_known
    b, j = sorted(rng.sample(range(len(track)), 2))
    xt = 0.0 if not heading_known else rng.uniform(-0.01, 0.01)  # (the unknown-heading mode keeps none)
    p = (0.04, 0.01, xt, 0.09, -xt, 0.2)
    state = (rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(-3, 3), p)
    closed = track.across(b, j, state, heading_known=heading_known)
    stepped = _stepwise(track, b, j, state, predictor)
    assert math.isclose(closed[0], stepped[0], abs_tol=1e-9)
    assert math.isclose(closed[1], stepped[1], abs_tol=1e-9)
    assert abs(ekf.wrap_angle(closed[2] - stepped[2])) < 1e-9
    scale = max(abs(v) for v in stepped[3])
    assert all(abs(u - v) <= 1e-10 * scale for u, v in zip(closed[3], stepped[3], strict=True)), (closed, stepped)


def _fix_stream(seed: int) -> list[tuple[float, float, float, float]]:
    """Fixes (arrival, x, y, measured) of a robot going along x at 0.3 m/s, 8 Hz, 50-150 ms late."""
    rng = random.Random(seed)
    out = []
    for k in range(1, 60):
        t_meas = 0.125 * k
        out.append((t_meas + rng.uniform(0.05, 0.15), 0.3 * t_meas + rng.gauss(0, 0.02), rng.gauss(0, 0.02), t_meas))
    return out


def _twists(est: Estimator, until: float) -> None:
    t = 0.0
    while t < until:
        t = round(t + 0.01, 6)
        est.on_twist(t, 0.3, 0.0, 0.0)


def _run(fixes: list[tuple[float, float, float, float]], config: EkfConfig) -> Estimator:
    """Fixes and twists in arrival order."""
    est = Estimator(config, GEOMETRY, (0.05, 0.0), CPR)
    events = sorted(
        [(a, 1, (a, x, y, m)) for a, x, y, m in fixes] + [(round(0.01 * i, 6), 0, None) for i in range(1, 900)]
    )
    for t, kind, fix in events:
        if kind == 0:
            est.on_twist(t, 0.3, 0.0, 0.0)
        else:
            assert fix is not None
            est.on_fix(*fix)
    return est


def test_a_fix_arriving_after_a_later_measured_one_lands_in_its_place() -> None:
    config = dataclasses.replace(
        EkfConfig(), adaptive_ips_noise=False, gating=False, initial_sigma=(1.0, 1.0, 0.1), heading_align_m=0.0
    )
    fixes = _fix_stream(3)
    swapped = [*fixes]
    for k in range(6, len(fixes) - 1, 7):  # every seventh fix (after the seeding ones) overtakes the one before it
        (_, x1, y1, m1), (a2, x2, y2, m2) = swapped[k], swapped[k + 1]
        swapped[k], swapped[k + 1] = (a2 + 0.002, x1, y1, m1), (a2 + 0.001, x2, y2, m2)
    assert any(swapped[k][0] > swapped[k + 1][0] and swapped[k][3] < swapped[k + 1][3] for k in range(len(swapped) - 1))
    in_order, overtaken = _run(fixes, config), _run(swapped, config)
    a, b = in_order.pose(), overtaken.pose()
    assert math.isclose(a.x, b.x, abs_tol=1e-9)
    assert math.isclose(a.y, b.y, abs_tol=1e-9)
    assert all(math.isclose(u, v, abs_tol=1e-12) for u, v in zip(a.cov, b.cov, strict=True))


@given(st.lists(st.floats(-1.0, 1.0, allow_nan=False), min_size=1, max_size=120))
def test_the_noise_estimates_running_median_is_the_median_of_the_window(values: list[float]) -> None:
    gate = FixGate(
        EkfConfig(), dict.fromkeys(("fixes_accepted", "fixes_rejected", "recoveries", "fixes_seeded"), 0), paper=False
    )
    for v in values:
        inn = ekf.Innovation(math.sqrt(abs(v)), 0.0, 2 * gate.r, 0.0, 2 * gate.r, 0.0, 0.0, 0.0)
        gate._learn_noise(inn, gate.r)
        window = sorted(gate.innovations)
        assert gate._ordered == window


