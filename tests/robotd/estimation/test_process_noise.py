"""The process noise scale learnt by a bank of shadow filters (robotd.estimation.process_noise)."""

from __future__ import annotations

import math
import random
import statistics

from robotd.estimation.process_noise import ProcessNoiseScale

POSITION_VAR_PER_M = 0.5 * (0.02**2 + 0.03**2)  # the default odometry noise's, per axis
FIX_VAR = 0.02**2  # a 2 cm IPS
STEP_M = 0.03  # driven between two fixes: 0.3 m/s, fixes at 10 Hz


def drive(
    true_scale: float,
    fixes: int,
    seed: int,
    *,
    told_fix_var: float = FIX_VAR,
    step_m: float = STEP_M,
    learn: bool = True,
    scale: ProcessNoiseScale | None = None,
) -> ProcessNoiseScale:
    """A robot whose position drifts by true_scale times the configured odometry noise, tracked by a filter that
    predicts with the learnt scale (as robotd's does) and is told the fix noise `told_fix_var`; the scale after."""
    rng = random.Random(seed)
    if scale is None:
        scale = ProcessNoiseScale(0.01, 4.0, position_var_per_m=POSITION_VAR_PER_M)
    truth, estimate, variance, distance = [0.0, 0.0], [0.0, 0.0], 0.0, 0.0
    for _ in range(fixes):
        distance += step_m
        truth = [v + rng.gauss(0.0, math.sqrt(true_scale * POSITION_VAR_PER_M * step_m)) for v in truth]
        variance += scale.value * POSITION_VAR_PER_M * step_m
        fix = [v + rng.gauss(0.0, math.sqrt(FIX_VAR)) for v in truth]
        s = variance + told_fix_var
        nu = (fix[0] - estimate[0], fix[1] - estimate[1])
        scale.on_innovation(nu, s, told_fix_var, distance, learn=learn)
        gain = variance / s
        estimate = [estimate[0] + gain * nu[0], estimate[1] + gain * nu[1]]
        variance *= 1.0 - gain
    return scale


def learnt(true_scale: float, fixes: int, *, told_fix_var: float = FIX_VAR) -> list[float]:
    """The scale after `fixes` fixes, over ten seeded runs."""
    return [drive(true_scale, fixes, seed, told_fix_var=told_fix_var).value for seed in range(10)]


def geometric_mean(values: list[float]) -> float:
    """The mean in log space, where scales are judged."""
    return math.exp(statistics.fmean(math.log(v) for v in values))


def test_a_flat_floor_is_found_within_half_a_minute_and_a_rough_one_keeps_its_noise() -> None:
    # 300 fixes: 30 s of driving. The likelihood tells small scales apart only slowly (the fixes' noise dwarfs the
    # drift between two of them), so a hundredth is found as a few hundredths: far from the prior, 1
    flat = learnt(0.01, 300)
    assert max(flat) < 0.1
    assert 0.1 / 1.6 < geometric_mean(learnt(0.1, 300)) < 0.1 * 1.6
    assert 1.0 / 1.4 < geometric_mean(learnt(1.0, 300)) < 1.0 * 1.4
    assert min(learnt(4.0, 300)) > 2.0  # a floor rougher than configured: the noise goes up


def test_a_fix_noise_told_wrong_does_not_pass_for_process_noise() -> None:
    # the shadows assume fix noises about the one told: a filter told half the truth sees innovations larger than
    # its prediction, which a bank of one fix noise could explain only by drift
    assert max(learnt(0.01, 300, told_fix_var=0.5 * FIX_VAR)) < 0.1
    assert max(learnt(0.01, 300, told_fix_var=2.0 * FIX_VAR)) < 0.1


def test_the_scale_stays_within_its_bounds() -> None:
    still = drive(1e-4, 600, 1)
    assert 0.01 <= still.value < 0.05
    rough = drive(100.0, 300, 2)
    assert 3.0 < rough.value <= 4.0


def test_nothing_is_learnt_when_not_asked_or_at_rest() -> None:
    for scale in (drive(0.01, 300, 3, learn=False), drive(0.01, 300, 3, step_m=0.0)):
        assert scale.value == 1.0
        assert scale.learnt == 0


def test_a_scale_learnt_before_is_where_the_prior_is_and_reset_goes_back_to_1() -> None:
    before = drive(0.01, 300, 4)
    started = ProcessNoiseScale(0.01, 4.0, before.value, position_var_per_m=POSITION_VAR_PER_M)
    assert started.value == before.value
    assert drive(0.01, 30, 5, scale=started).value < 0.1  # a few fixes do not undo what a run learnt
    assert started.reset()
    assert started.value == 1.0
    assert not started.reset()  # already at the prior
    assert ProcessNoiseScale(0.01, 4.0, math.nan, position_var_per_m=POSITION_VAR_PER_M).value == 1.0


def test_a_forgotten_fix_restarts_the_shadows_from_the_filter() -> None:
    scale = ProcessNoiseScale(0.01, 4.0, position_var_per_m=POSITION_VAR_PER_M)
    assert not scale.on_innovation((0.0, 0.0), 2.0 * FIX_VAR, FIX_VAR, 0.0, learn=True)  # places the shadows
    assert scale.learnt == 0
    scale.on_innovation((0.01, 0.0), 2.0 * FIX_VAR, FIX_VAR, 0.03, learn=True)
    assert scale.learnt == 1
    scale.forget()  # a rejected fix came between
    # the next fix only places the shadows again: their offsets were from a position that is no longer robotd's
    assert not scale.on_innovation((0.5, 0.5), 2.0 * FIX_VAR, FIX_VAR, 0.06, learn=True)
    assert scale.learnt == 1
