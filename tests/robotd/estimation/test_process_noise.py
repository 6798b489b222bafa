"""The process noise scale learnt from the whiteness of innovations (robotd.estimation.process_noise)."""

from __future__ import annotations

import math
import random
import statistics

from robotd.estimation.process_noise import SPAN_S, STEP, STEP_SETTLED, ProcessNoiseScale

PERIOD_S = 0.1  # a fix every 0.1 s, the robot driving 0.3 m/s


def feed(scale: ProcessNoiseScale, innovations: list[tuple[float, float]], *, speed: float = 0.3) -> list[float]:
    """Accepted fixes with these innovations (unit predicted variance), one per PERIOD_S, learning from each; the
    scale after each."""
    values = []
    for k, nu in enumerate(innovations):
        t = k * PERIOD_S
        scale.on_innovation(t, nu, 1.0, (speed * t, 0.0), learn=True)
        values.append(scale.value)
    return values


def sequence(n: int, seed: int, *, chased: float = 0.0, persist: float = 0.0) -> list[tuple[float, float]]:
    """Innovations e_k - chased * e_(k-1) of white e (a filter chasing each fix's noise), or AR(1) of lag-one
    correlation `persist` (drift left unfollowed)."""
    rng = random.Random(seed)
    out, before, state = [], (0.0, 0.0), (0.0, 0.0)
    for _ in range(n):
        e = (rng.gauss(0.0, 1.0), rng.gauss(0.0, 1.0))
        if persist:
            state = (persist * state[0] + e[0], persist * state[1] + e[1])
            out.append(state)
        else:
            out.append((e[0] - chased * before[0], e[1] - chased * before[1]))
        before = e
    return out


def mean_log_scale(**kind: float) -> float:
    """The mean log of the scale after 10 s of such innovations (100 fixes at 10 Hz), over 20 runs, with bounds far
    enough (0.01, 100) that none of them is reached."""
    logs = []
    for seed in range(20):
        scale = ProcessNoiseScale(0.01, 100.0)
        feed(scale, sequence(100, 100 + seed, **kind))
        logs.append(math.log(scale.value))
    return statistics.fmean(logs)


def test_the_scale_goes_down_when_the_filter_chases_the_fixes_noise_and_up_when_innovations_persist() -> None:
    # each run wanders (no filter pulls it back here: about 1.3 in log after 100 fixes, so a mean of 20 within about
    # 0.3 of the truth); on average it is unbiased
    assert abs(mean_log_scale()) < 0.6
    assert mean_log_scale(chased=0.5) < -0.8
    assert mean_log_scale(persist=0.6) > 0.8


def test_the_scale_stays_within_its_bounds() -> None:
    down = ProcessNoiseScale(0.1, 4.0)
    values = feed(down, sequence(5000, 2, chased=0.8))
    assert min(values) == 0.1  # never trusts odometry more than the configuration allows
    up = ProcessNoiseScale(0.1, 4.0)
    values = feed(up, sequence(5000, 4, persist=0.8))
    assert max(values) == 4.0


def test_nothing_is_learnt_when_not_asked_or_at_rest() -> None:
    chasing = sequence(300, 8, chased=0.8)
    for scale, speed, learn in (
        (ProcessNoiseScale(0.1, 4.0), 0.0, True),  # at rest: the odometry added no noise
        (ProcessNoiseScale(0.1, 4.0), 0.3, False),  # correlated fixes, or the heading unknown
    ):
        for k, nu in enumerate(chasing):
            t = k * PERIOD_S
            scale.on_innovation(t, nu, 1.0, (speed * t, 0.0), learn=learn)
        assert scale.value == 1.0
        assert scale.pairs == 0


def test_pairs_never_span_a_forgotten_fix_or_a_gap_longer_than_the_span() -> None:
    scale = ProcessNoiseScale(0.1, 4.0)
    scale.on_innovation(0.0, (1.0, 0.0), 1.0, (0.0, 0.0), learn=True)
    scale.on_innovation(0.1, (-1.0, 0.0), 1.0, (0.03, 0.0), learn=True)
    assert scale.pairs == 1
    assert scale.value < 1.0  # opposite innovations: chased noise
    scale.forget()  # a rejected fix or a seed came between
    before = scale.value
    scale.on_innovation(0.2, (1.0, 0.0), 1.0, (0.06, 0.0), learn=True)
    assert (scale.pairs, scale.value) == (1, before)
    scale.on_innovation(0.2 + SPAN_S + 0.1, (1.0, 0.0), 1.0, (1.0, 0.0), learn=True)
    assert (scale.pairs, scale.value) == (1, before)


def test_the_step_shrinks_once_the_scale_settles_and_grows_back_when_the_innovations_persist() -> None:
    for seed in range(5):
        leaving = ProcessNoiseScale(0.01, 100.0)
        feed(leaving, sequence(100, 10 + seed, chased=0.8))
        assert leaving.step == STEP  # leaving a wrong prior: every block says the same, the step stays large
    scale = ProcessNoiseScale(0.01, 100.0)
    feed(scale, sequence(1500, 6))  # white: the summed correlation changes sign from block to block
    assert scale.step == STEP_SETTLED
    steps = []
    for k in range(300):  # then the floor changes: a drift no longer followed, innovations of one sign
        t = (1500 + k) * PERIOD_S
        scale.on_innovation(t, (1.0, 0.5), 1.0, (0.3 * t, 0.0), learn=True)
        steps.append(scale.step)
    assert steps[0] == STEP_SETTLED
    assert steps[-1] == STEP  # back within (GROW_AFTER + log(STEP / STEP_SETTLED) / -log(SHRINK)) blocks
    scale.reset()
    assert (scale.value, scale.step) == (1.0, STEP)
