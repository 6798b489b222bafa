"""The odometry track, the anchors' history carried step by step, and the trimmed daemon estimator."""

from __future__ import annotations

import dataclasses
import itertools
import math
import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robotd import kinematics
from robotd.config.model import EkfConfig
from robotd.estimation import ekf, estimator
from robotd.estimation.estimator import Estimator
from robotd.estimation.fixgate import NOISE_PRIOR_SAMPLES, FixGate
from robotd.estimation.heading import LN4
from robotd.estimation.history import Anchor, History, Predictor, State
from robotd.estimation.modes import Modes, Verdict
from robotd.estimation.track import OdometryTrack

GEOMETRY = kinematics.Geometry()
CPR = 6800
NOISE = ekf.ControlNoise(lin2=4e-4, lat2=9e-4, slip2=2.5e-3, turn2=2.5e-3)


def _random_track(rng: random.Random, n: int) -> OdometryTrack:
    track = OdometryTrack(midpoint=True)
    track.start(0.0, (0.0, 0.0, 0.0))
    t = 0.0
    for _ in range(n):
        t += rng.uniform(0.01, 0.2)
        u = (rng.uniform(-0.6, 0.6), rng.uniform(-0.4, 0.4), rng.uniform(-2.0, 2.0))
        track.append(t, u, u)
    return track


def _piecewise(track: OdometryTrack, state: State, start: float, end: float, predictor: Predictor) -> State:
    """The state moved from `start` to `end` in pieces cut at the step ends, each with its step's twist (the newest
    step's held twist past it)."""
    cuts = [start] + [t for t in track.t if start < t < end] + [end]
    for a, b in itertools.pairwise(cuts):
        if b <= a:
            continue
        k = next((i for i, t in enumerate(track.t) if t >= b), None)
        u = (track.vx[k], track.vy[k], track.wz[k]) if k is not None else (track.hx[-1], track.hy[-1], track.hw[-1])
        state = predictor.move(state, u, b - a)
    return state


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 10_000), st.booleans())
def test_the_state_at_any_time_is_the_anchor_moved_across_each_step_in_force(seed: int, heading_known: bool) -> None:
    rng = random.Random(seed)
    track = _random_track(rng, 30)
    predictor = Predictor(NOISE, Modes(heading_known=heading_known), midpoint=True)
    start = rng.uniform(0.0, track.t[-1])
    end = start + rng.choice((0.0, rng.uniform(0.0, 0.3), rng.uniform(0.0, track.t[-1])))  # within, across, past
    end = rng.choice((end, next((t for t in track.t if t > start), end)))  # and exactly at a step's end
    anchor = Anchor(
        start, rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(-3, 3), (0.04, 0.01, 0.0, 0.09, 0.0, 0.2), None
    )
    history = History(track, predictor, anchor, 1.0, keep_past=True)
    held = (track.hx[-1], track.hy[-1], track.hw[-1])
    got = history.state_at(anchor, end, lambda: held)
    assert got == _piecewise(track, anchor.state, start, end, predictor)


def test_the_odometry_pose_is_interpolated_between_steps_and_held_past_them() -> None:
    track = OdometryTrack(midpoint=True)
    track.start(1.0, (0.0, 0.0, 0.0))
    track.append(2.0, (0.5, 0.0, 0.0), (0.5, 0.0, 0.0))
    track.append(3.0, (0.0, 0.5, 0.0), (0.0, 0.0, 0.0))
    assert track.pose_at(0.5) is None
    assert track.pose_at(1.5) == pytest.approx((0.25, 0.0, 0.0))
    assert track.pose_at(2.5) == pytest.approx((0.5, 0.25, 0.0))
    assert track.pose_at(9.0) == pytest.approx((0.5, 0.5, 0.0))
    assert track.dist[-1] == pytest.approx(1.0)
    assert track.twist_at(2.5) == (0.0, 0.5, 0.0)
    assert track.twist_at(9.0) is None


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
    config = dataclasses.replace(  # (calibration learns from fixes in arrival order: off, as the noise estimate)
        EkfConfig(),
        adaptive_ips_noise=False,
        gating=False,
        initial_sigma=(1.0, 1.0, 0.1),
        heading_align_m=0.0,
        calibrate=False,
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
        EkfConfig(),
        dict.fromkeys(("fixes_accepted", "fixes_rejected", "recoveries", "fixes_seeded"), 0),
        Modes(heading_known=True),
    )
    for v in values:
        inn = ekf.Innovation(math.sqrt(abs(v)), 0.0, 2 * gate.r, 0.0, 2 * gate.r, 0.0, 0.0, 0.0)
        gate._learn_noise(inn, gate.r)
        window = sorted(gate.innovations)
        assert gate._ordered == window


def _outage_run(config: EkfConfig) -> tuple[Estimator, int]:
    """5 minutes of wheels at 100 Hz; fixes for the first 20 s, then none (a long outage); the longest track held."""
    rng = random.Random(4)
    est = Estimator(config, GEOMETRY, (0.0, 0.0), CPR)
    counts = [0, 0, 0, 0]
    longest = 0
    for i in range(30_000):
        t = 0.01 * (i + 1)
        counts = [c + d for c, d in zip(counts, (10, 12, 11, 9), strict=True)]
        est.on_wheels(t, (counts[0], counts[1], counts[2], counts[3]))
        if i % 12 == 0 and i < 2000:
            est.on_fix(t + 0.005, rng.gauss(0, 0.02), rng.gauss(0, 0.02), t - 0.05)
        longest = max(longest, len(est._track))
    return est, longest


def test_a_long_outage_keeps_the_daemons_history_short_and_the_estimate_unchanged(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Fed one sample at a time, the estimator trims its track; an estimator that never trims agrees with it."""
    config = dataclasses.replace(EkfConfig(), initial_sigma=(1.0, 1.0, 0.1))
    daemon, longest = _outage_run(config)
    monkeypatch.setattr(estimator, "TRIM_STEPS", 10**9)
    untrimmed, held = _outage_run(config)
    assert longest < 1000  # 50 s of steps at most, not 5 minutes' 6000
    assert held > 5000
    a, b = daemon.pose(), untrimmed.pose()
    assert math.isclose(a.x, b.x, abs_tol=1e-9)
    assert math.isclose(a.y, b.y, abs_tol=1e-9)
    assert all(math.isclose(u, v, rel_tol=1e-9, abs_tol=1e-15) for u, v in zip(a.cov, b.cov, strict=True))


def _silent_odometry_run() -> tuple[Estimator, int]:
    """One wheel sample, then 20 minutes of fixes at 16 Hz with the odometry silent (a robot at rest whose stream
    publishes only changes, an unplugged encoder); the most anchors held."""
    rng = random.Random(5)
    est = Estimator(EkfConfig(), GEOMETRY, (0.0, 0.0), CPR)
    est.on_wheels(0.0, (0, 0, 0, 0))
    most = 0
    for i in range(16 * 1200):
        t = (i + 1) / 16
        est.on_fix(t, 1.0 + rng.gauss(0, 0.02), 2.0 + rng.gauss(0, 0.02), t - 0.05)
        most = max(most, len(est._history.anchors))
    return est, most


def test_silent_odometry_keeps_the_anchors_few_and_the_estimate_unchanged(monkeypatch: pytest.MonkeyPatch) -> None:
    """The track never grows, so its trimming never ran: every fix's anchor was kept (about 1 MB a minute)."""
    daemon, most = _silent_odometry_run()
    monkeypatch.setattr(estimator, "TRIM_ANCHORS", 10**9)
    untrimmed, held = _silent_odometry_run()
    assert most <= estimator.TRIM_ANCHORS + 1
    assert held > 16 * 1100
    a, b = daemon.pose(), untrimmed.pose()
    assert (a.x, a.y) == pytest.approx((1.0, 2.0), abs=0.01)
    assert math.isclose(a.x, b.x, abs_tol=1e-12)
    assert math.isclose(a.y, b.y, abs_tol=1e-12)
    assert all(math.isclose(u, v, rel_tol=1e-9, abs_tol=1e-15) for u, v in zip(a.cov, b.cov, strict=True))


def _gate(config: EkfConfig) -> FixGate:
    return FixGate(
        config,
        dict.fromkeys(("fixes_accepted", "fixes_rejected", "recoveries", "fixes_seeded"), 0),
        Modes(heading_known=True),
    )


def _learn_from(gate: FixGate, sigma: float, *, lower: bool = True) -> None:
    """Give the gate's noise estimate 40 innovations whose median is that of an IPS of `sigma` (P = 0: S = R), the
    estimate allowed below the noise in use only when `lower`."""
    for _ in range(40):
        inn = ekf.Innovation(sigma * math.sqrt(LN4), 0.0, gate.r, 0.0, gate.r, 0.0, 0.0, 0.0)
        gate._learn_noise(inn, gate.r, lower=lower)


def test_the_noise_estimate_goes_below_the_configured_sigma_only_once_the_fixes_are_judged() -> None:
    gate = _gate(EkfConfig(ips_sigma_m=0.03, ips_sigma_min_m=0.005))
    quiet = 0.01  # innovations of a 1 cm IPS, whose median says so
    _learn_from(gate, quiet)
    assert gate.r == pytest.approx(0.03**2)  # the configured sigma is the prior until the fixes are judged
    gate.trust_quieter_fixes(0.0)
    _learn_from(gate, quiet)
    assert gate.r == pytest.approx(quiet**2, rel=0.05)


@pytest.mark.parametrize(("assumed", "true"), [(0.03, 0.02), (0.05, 0.01), (0.01, 0.03)])
def test_the_noise_estimate_at_rest_is_the_true_noise_though_the_prediction_is_made_with_the_assumed(
    assumed: float, true: float
) -> None:
    """A robot at rest: its estimate is the mean of the n fixes so far, whose variance the filter puts at r / n with
    the noise r in use; the innovations (here each at its median) have the true noise's (1 + 1 / n)."""
    gate = _gate(EkfConfig(ips_sigma_m=assumed, ips_sigma_min_m=0.005, ips_sigma_max_m=0.3))
    gate.trust_quieter_fixes(0.0)
    learnt = []
    for n in range(1, 41):
        r = gate.r
        s = r + r / n
        inn = ekf.Innovation(math.sqrt(LN4 * (true**2 + true**2 / n)), 0.0, s, 0.0, s, 0.0, 0.0, 0.0)
        gate._learn_noise(inn, r)
        learnt.append(math.sqrt(gate.r))
    # once the window's samples outweigh the prior (NOISE_PRIOR_SAMPLES), every estimate is the truth: subtracting
    # the predicted r / n instead put a 1 cm IPS assumed at 5 cm on the 5 mm floor
    majority = NOISE_PRIOR_SAMPLES // 2 + 1
    assert learnt[: majority - 1] == [assumed] * (majority - 1)
    assert all(value == pytest.approx(true, rel=0.01) for value in learnt[majority - 1 :]), learnt


def test_a_few_quiet_innovations_do_not_move_the_noise_estimate_a_majority_of_its_prior_samples_does() -> None:
    # a median of five 2-dof chi-square draws falls below 0.4x the truth one time in ten: on a real robot's run with
    # 4 Hz fixes it put a 3 cm IPS at the 5 mm floor, and the next fix, fused at 5 mm, turned the heading 34 degrees
    gate = _gate(EkfConfig(ips_sigma_m=0.03, ips_sigma_min_m=0.005))
    gate.trust_quieter_fixes(0.0)
    prior, taken = gate.r, []
    for _ in range(NOISE_PRIOR_SAMPLES):
        inn = ekf.Innovation(0.001, 0.0, gate.r, 0.0, gate.r, 0.0, 0.0, 0.0)  # far quieter than the prior
        gate._learn_noise(inn, gate.r)
        taken.append(gate.r)
    majority = NOISE_PRIOR_SAMPLES // 2 + 1
    assert taken[: majority - 1] == [prior] * (majority - 1)  # fewer than half of the prior's weight: held
    assert taken[majority - 1] == pytest.approx(0.005**2)  # then they outweigh it, down to the floor
    gate.forget()  # a re-alignment or a recovery: the window starts again, leaning on the noise now in use
    for _ in range(majority - 1):
        loud = ekf.Innovation(0.05 * math.sqrt(LN4), 0.0, gate.r, 0.0, gate.r, 0.0, 0.0, 0.0)
        gate._learn_noise(loud, gate.r)
    assert gate.r == pytest.approx(0.005**2)


def test_a_noise_learnt_below_the_truth_gates_only_what_the_configured_noise_would() -> None:
    config = EkfConfig(ips_sigma_m=0.03, ips_sigma_min_m=0.005, seed_fixes=0)
    gate = _gate(config)
    gate.trust_quieter_fixes(0.0)
    _learn_from(gate, 0.005)  # a few quiet innovations put a 2 cm IPS's noise at the 5 mm floor
    assert gate.r == pytest.approx(0.005**2)
    p = 0.01**2  # the prediction's variance per axis

    def verdict(nu: float) -> Verdict:
        s = p + gate.r
        return gate.judge(0.0, ekf.Innovation(nu, 0.0, s, 0.0, s, nu * nu / s, 0.0, 0.0), gate.r, learn=False)

    # 6 cm is 2.7 sigma of the 2 cm IPS, and 5.4 sigma of the learnt noise: an ordinary fix, gated on the 5 mm
    assert verdict(0.06) is Verdict.ACCEPTED
    assert verdict(0.5) is Verdict.GATED  # an echo is as far outside the configured noise's gate as the learnt's


def test_fixes_judged_correlated_keep_the_noise_the_judging_fit_saw() -> None:
    # the filter follows a persistent fix error, so the innovations see only its changes from fix to fix: on the libRSF
    # UWB run (fix errors of 0.15 m lasting seconds) they put the noise at the 5 mm floor
    config = EkfConfig(ips_sigma_m=0.03, ips_sigma_min_m=0.005)
    gate = _gate(config)
    gate.trust_quieter_fixes(0.08**2)  # a fit found their errors persisting, with 8 cm of noise
    assert gate.r == pytest.approx(0.08**2)  # taken at once, not only when the next innovations come
    quiet = 0.01
    _learn_from(gate, quiet)
    assert gate.r == pytest.approx(0.08**2)
    loud = 0.12  # a noisier IPS is still followed above that floor
    _learn_from(gate, loud)
    assert gate.r == pytest.approx(loud**2, rel=0.05)
    gate.trust_quieter_fixes(0.0)  # judged independent after all: the quiet innovations are believed again
    _learn_from(gate, quiet)
    assert gate.r == pytest.approx(quiet**2, rel=0.05)
    gate.trust_quieter_fixes(1.0)  # never above the configured ceiling
    assert gate.r == pytest.approx(config.ips_sigma_max_m**2)


def test_a_noise_learnt_while_the_heading_is_unknown_may_rise_but_not_fall() -> None:
    # a prediction along a heading not known is wider than the truth, so the innovations less it are a lower bound
    # of the noise: on the libRSF robot's harsh log they took a 3 cm IPS to 1.7 cm by the first re-alignment
    gate = _gate(EkfConfig(ips_sigma_m=0.03, ips_sigma_min_m=0.005))
    gate.trust_quieter_fixes(0.0)
    _learn_from(gate, 0.005, lower=False)
    assert gate.r == pytest.approx(0.03**2)
    gate.forget()
    _learn_from(gate, 0.08, lower=False)
    assert gate.r == pytest.approx(0.08**2, rel=0.05)
