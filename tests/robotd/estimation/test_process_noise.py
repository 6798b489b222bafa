"""The process noise scales learnt by a bank of shadow filters (robotd.estimation.process_noise)."""

from __future__ import annotations

import math
import random
import statistics

from robotd.estimation import ekf
from robotd.estimation.process_noise import OdometryNoise, Pose, ProcessNoiseScale, Travel

# the default odometry noise's: position per axis and metre, heading per metre (slip); no turning here
NOISE = OdometryNoise(0.5 * (0.02**2 + 0.03**2), 0.05**2, 0.05**2)
FIX_VAR = 0.02**2  # a 2 cm IPS
STEP_M = 0.03  # driven between two fixes: 0.3 m/s, fixes at 10 Hz


def bank(position: float = 1.0, heading: float = 1.0) -> ProcessNoiseScale:
    return ProcessNoiseScale(0.01, 4.0, position, heading, noise=NOISE)


def drive(
    true_scale: float,
    fixes: int,
    seed: int,
    *,
    true_heading: float | None = None,
    told_fix_var: float = FIX_VAR,
    step_m: float = STEP_M,
    learn: bool = True,
    scale: ProcessNoiseScale | None = None,
) -> ProcessNoiseScale:
    """A robot driving straight whose position drifts by true_scale times the configured position noise and whose
    heading by true_heading (default: true_scale) times the heading's, tracked by a 3-state EKF that predicts with the
    learnt scales (as robotd's does) and is told the fix noise `told_fix_var`; the scales after."""
    rng = random.Random(seed)
    scale = bank() if scale is None else scale
    heading_scale = true_scale if true_heading is None else true_heading
    truth = [0.0, 0.0, 0.0]
    x, y, th = 0.0, 0.0, 0.0
    p = (FIX_VAR, 0.0, 0.0, FIX_VAR, 0.0, 0.01)
    distance = 0.0
    for k in range(fixes):
        distance += step_m
        # the truth: driven along its heading, which wanders; the position wanders too
        truth[2] += rng.gauss(0.0, math.sqrt(heading_scale * NOISE.heading_var_per_m * step_m))
        for axis, along in ((0, math.cos(truth[2])), (1, math.sin(truth[2]))):
            wander = rng.gauss(0.0, math.sqrt(true_scale * NOISE.position_var_per_m * step_m))
            truth[axis] += step_m * along + wander
        # the filter's prediction: F P F^T + Q, the Q of the scales in use
        dx, dy = step_m * math.cos(th), step_m * math.sin(th)
        x, y = x + dx, y + dy
        xx, xy, xt, yy, yt, tt = p
        a, b = -dy, dx
        q_position = scale.value * NOISE.position_var_per_m * step_m
        q_heading = scale.heading_value * NOISE.heading_var_per_m * step_m
        p = (
            xx + 2 * a * xt + a * a * tt + q_position,
            xy + a * yt + b * xt + a * b * tt,
            xt + a * tt,
            yy + 2 * b * yt + b * b * tt + q_position,
            yt + b * tt,
            tt + q_heading,
        )
        prior = Pose(x, y, th, p)
        inn = ekf.innovation(
            x,
            y,
            th,
            p,
            truth[0] + rng.gauss(0.0, FIX_VAR**0.5),
            truth[1] + rng.gauss(0.0, FIX_VAR**0.5),
            told_fix_var,
            0,
            0,
        )
        x, y, th, p = ekf.update(x, y, th, p, inn, told_fix_var)
        scale.on_fix(
            0.1 * (k + 1),
            inn,
            told_fix_var,
            prior,
            Pose(x, y, th, p),
            Travel(distance, 0.0),
            learn=learn,
            freeze_heading=False,
        )
    return scale


def learnt(true_scale: float, fixes: int, **options: float) -> list[ProcessNoiseScale]:
    """The scales after `fixes` fixes, over ten seeded runs."""
    return [drive(true_scale, fixes, seed, **options) for seed in range(10)]  # type: ignore[arg-type]


def geometric_mean(values: list[float]) -> float:
    """The mean in log space, where scales are judged."""
    return math.exp(statistics.fmean(math.log(v) for v in values))


def test_a_flat_floor_is_found_within_half_a_minute_and_a_rough_one_keeps_its_noise() -> None:
    # 300 fixes: 30 s of driving. The likelihood tells small scales apart only slowly (the fixes' noise dwarfs the
    # drift between two of them), so a hundredth is found as a few hundredths: far from the prior, 1
    flat = learnt(0.01, 300)
    assert max(s.value for s in flat) < 0.1
    assert 0.1 / 1.6 < geometric_mean([s.value for s in learnt(0.1, 300)]) < 0.1 * 1.6
    assert 1.0 / 1.4 < geometric_mean([s.value for s in learnt(1.0, 300)]) < 1.0 * 1.4
    assert min(s.value for s in learnt(4.0, 300)) > 2.0  # a floor rougher than configured: the noise goes up


def test_the_headings_noise_is_learnt_apart_from_the_positions() -> None:
    # a flat floor that still turns the robot (unequal traction), and a rough floor that does not: one scale for both
    # could be right for only one of the two terms. A heading error shows as a drift across the direction of travel
    # that grows with the distance driven, which a position random walk does not; it is learnt more slowly
    turning = learnt(0.01, 600, true_heading=1.0)
    assert max(s.value for s in turning) < 0.2
    assert 0.5 < geometric_mean([s.heading_value for s in turning]) < 2.0
    assert min(s.heading_value for s in turning) > 0.3
    straight = learnt(1.0, 600, true_heading=0.01)
    assert 1.0 / 1.4 < geometric_mean([s.value for s in straight]) < 1.0 * 1.4
    assert max(s.heading_value for s in straight) < 0.25


def test_a_fix_noise_told_wrong_does_not_pass_for_process_noise() -> None:
    # the shadows assume fix noises about the one told: a filter told half the truth sees innovations larger than
    # its prediction, which a bank of one fix noise could explain only by drift
    assert max(s.value for s in learnt(0.01, 300, told_fix_var=0.5 * FIX_VAR)) < 0.1
    assert max(s.value for s in learnt(0.01, 300, told_fix_var=2.0 * FIX_VAR)) < 0.1


def test_the_scales_stay_within_their_bounds() -> None:
    still = drive(1e-4, 600, 1)
    assert min(still.value, still.heading_value) >= 0.01
    assert max(still.value, still.heading_value) < 0.05
    rough = drive(100.0, 300, 2)
    assert min(rough.value, rough.heading_value) > 3.0
    assert max(rough.value, rough.heading_value) <= 4.0


def test_nothing_is_learnt_when_not_asked_or_at_rest() -> None:
    for scale in (drive(0.01, 300, 3, learn=False), drive(0.01, 300, 3, step_m=0.0)):
        assert (scale.value, scale.heading_value) == (1.0, 1.0)
        assert scale.learnt == 0


def test_scales_learnt_before_are_where_the_prior_is_and_reset_goes_back_to_1() -> None:
    before = drive(0.01, 300, 4)
    started = bank(before.value, before.heading_value)
    assert (started.value, started.heading_value) == (before.value, before.heading_value)
    assert drive(0.01, 30, 5, scale=started).value < 0.1  # a few fixes do not undo what a run learnt
    assert started.reset()
    assert (started.value, started.heading_value) == (1.0, 1.0)
    assert not started.reset()  # already at the prior
    assert (bank(math.nan, math.inf).value, bank(math.nan, math.inf).heading_value) == (1.0, 1.0)


def test_a_forgotten_fix_restarts_the_shadows_from_the_filter() -> None:
    scale = bank()
    p = (FIX_VAR, 0.0, 0.0, FIX_VAR, 0.0, 0.01)
    here = Pose(0.0, 0.0, 0.0, p)

    def fix(t: float, nu: float, distance: float) -> bool:
        inn = ekf.innovation(0.0, 0.0, 0.0, p, nu, nu, FIX_VAR, 0.0, 0.0)
        return scale.on_fix(t, inn, FIX_VAR, here, here, Travel(distance, 0.0), learn=True, freeze_heading=False)

    assert not fix(0.1, 0.0, 0.0)  # places the shadows
    assert scale.learnt == 0
    fix(0.2, 0.01, 0.03)
    assert scale.learnt == 1
    scale.forget()  # a rejected fix came between
    # the next fix only places the shadows again: their offsets were from a pose that is no longer robotd's
    assert not fix(0.3, 0.5, 0.06)
    assert scale.learnt == 1
    fix(0.25, 0.0, 0.09)  # a fix measured before the last one: the shadows start again from it
    assert scale.learnt == 1
