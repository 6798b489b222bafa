"""The heading window's rotation fit: how certain it says it is, and what it tells of the fixes."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest
from fix_errors import ar1_errors

from robotd.estimation import heading
from robotd.estimation.heading import (
    MAX_FIT_SIGMA_RAD,
    FixSpread,
    HeadingAligner,
    HeadingCheck,
    RotationFit,
    trimmed_rotation_fit,
)
from robotd.estimation.modes import HeadingEvidence, HeadingMode


def _fit_with(errors: npt.NDArray[np.float64], rotation: float = 0.3) -> tuple[float, float, float, float, FixSpread]:
    """The fit of an arc of odometry points onto fixes: the arc turned by `rotation`, plus `errors`."""
    n = len(errors)
    s = np.linspace(0.0, 1.5, n)
    ox, oy = s, 0.2 * s * s  # a gently curving window of 1.5 m
    c, si = math.cos(rotation), math.sin(rotation)
    zx, zy = ox * c - oy * si + errors[:, 0], ox * si + oy * c + errors[:, 1]
    fit = trimmed_rotation_fit(ox.tolist(), oy.tolist(), zx.tolist(), zy.tolist(), 0.2)
    assert fit is not None
    return fit


def test_residuals_that_persist_from_fix_to_fix_make_the_rotation_as_uncertain_as_it_is() -> None:
    rng = np.random.default_rng(7)
    trials = 300
    white_errors: list[float] = []
    white_sigmas: list[float] = []
    correlated_errors: list[float] = []
    correlated_sigmas: list[float] = []
    for _ in range(trials):
        rotation, sigma, *_, spread = _fit_with(rng.normal(0.0, 0.03, (60, 2)))
        white_errors.append(rotation - 0.3)
        white_sigmas.append(sigma)
        assert spread.correlation < 0.5
        rotation, sigma, *_, spread = _fit_with(ar1_errors(rng, 60, 0.85, 0.03))
        correlated_errors.append(rotation - 0.3)
        correlated_sigmas.append(sigma)
    # the stated sigma matches the rotation's real spread, for independent fixes and for correlated ones alike
    for errors, sigmas in ((white_errors, white_sigmas), (correlated_errors, correlated_sigmas)):
        z = np.asarray(errors) / np.asarray(sigmas)
        assert 0.6 < float(np.std(z)) < 1.6
    assert float(np.median(correlated_sigmas)) > 2.0 * float(np.median(white_sigmas))


def test_a_heading_not_known_at_all_takes_even_an_uncertain_fit_one_already_known_does_not() -> None:
    fit = RotationFit(1.0, 2.0 * MAX_FIT_SIGMA_RAD, 0.0, 0.0, (0.0, 0.0, 0.0), 1, FixSpread(60, 0.03**2, 0.9))
    assert HeadingCheck().evidence(fit, 0.0, math.pi**2, HeadingMode.UNKNOWN) is HeadingEvidence.WHOLE_WINDOW
    assert HeadingCheck().evidence(fit, 0.0, 0.01, HeadingMode.ALIGNED) is None
    assert fit.sigma == pytest.approx(0.3)


def test_three_fixes_give_a_guide_whose_sigma_covers_its_error_once_the_noise_is_counted() -> None:
    # the estimator's provisional heading fits from three fixes (a 4 Hz beacon's first second of driving) and counts
    # the IPS noise in use when the few residuals understate it: so inflated, the sigma must cover the error
    rng = np.random.default_rng(11)
    ox, oy = [0.0, 0.1, 0.2], [0.0, 0.01, 0.03]
    noise, rotation = 0.02, 1.0
    c, s = math.cos(rotation), math.sin(rotation)
    assert trimmed_rotation_fit(ox, oy, ox, oy, 0.2) is None  # five points by default: enough to trim by a median
    z_scores = []
    for _ in range(400):
        e = rng.normal(0.0, noise, (3, 2))
        zx = [x * c - y * s + ex for x, y, ex in zip(ox, oy, e[:, 0], strict=True)]
        zy = [x * s + y * c + ey for x, y, ey in zip(ox, oy, e[:, 1], strict=True)]
        fit = trimmed_rotation_fit(ox, oy, zx, zy, 0.2, min_points=3)
        if fit is None:  # too uncertain to say anything (sigma beyond 0.5 rad)
            continue
        got, sigma, *_, spread = fit
        assert spread.correlation >= 0.0  # three residuals earn no credit for alternating
        inflated = sigma * math.sqrt(max(1.0, noise * noise / spread.variance))
        z_scores.append(abs(math.remainder(got - rotation, math.tau)) / inflated)
    assert len(z_scores) > 200
    assert np.mean(np.asarray(z_scores) <= 3.0) >= 0.97


def test_a_window_whose_track_has_not_moved_is_not_fitted_until_it_does(monkeypatch: pytest.MonkeyPatch) -> None:
    # at rest with the heading unknown the estimator asks for a fit at every fix, over a window that grows with every
    # fix: 0.17 ms a fix here at 12 Hz, a share of the daemon's 1 % budget at rest on a Pi; a still track has none
    fits: list[int] = []
    real_fit = heading.trimmed_rotation_fit

    def counted(*args: Any, **kwargs: Any) -> tuple[float, float, float, float, FixSpread] | None:
        fits.append(1)
        return real_fit(*args, **kwargs)

    monkeypatch.setattr(heading, "trimmed_rotation_fit", counted)
    aligner = HeadingAligner(1.5, (0.0, 0.0), enabled=True)
    aligner.restart(0.0, (0.2, 0.1, 0.4), 0.0)
    rng = np.random.default_rng(3)
    for i in range(200):
        aligner.record(1.0 + rng.normal(0, 0.02), 2.0 + rng.normal(0, 0.02), 0.1 * i, (0.2, 0.1, 0.4))
        assert aligner.fit_so_far(0.02**2) is None
    assert fits == []
    for i in range(1, 31):  # driving off along the window's x: now there is a track to fit
        x = 0.05 * i
        pose = (0.2 + x * math.cos(0.4), 0.1 + x * math.sin(0.4), 0.4)
        aligner.record(1.0 + x + rng.normal(0, 0.02), 2.0 + rng.normal(0, 0.02), 20.0 + 0.1 * i, pose)
    fit = aligner.fit_so_far(0.02**2)
    assert fits
    assert fit is not None
    assert abs(fit[0]) < 0.1  # the window's x is the fixes' x


def test_a_burst_of_outliers_while_the_robot_stood_still_does_not_turn_the_window() -> None:
    # config/sim-lab.yaml, random, seed 6, the heading unknown: 18 of a whole window's 71 fixes thrown 1-4.6 m away
    # while the robot stood still before it drove; least squares from all the points, trimmed from there, turned the
    # window by 1.37 rad (sigma 0.46), and the robot was placed 0.3-0.4 m off for four seconds
    rng = np.random.default_rng(5)
    rotation = 0.8
    c, s = math.cos(rotation), math.sin(rotation)
    ox = [0.0] * 36 + [0.035 * i for i in range(1, 36)]  # at rest, then 1.2 m gently curving
    oy = [0.0] * 36 + [0.1 * (0.035 * i) ** 2 for i in range(1, 36)]
    zx = [1.0 + x * c - y * s + rng.normal(0.0, 0.02) for x, y in zip(ox, oy, strict=True)]
    zy = [2.0 + x * s + y * c + rng.normal(0.0, 0.02) for x, y in zip(ox, oy, strict=True)]
    for i in range(7, 25):  # the burst, all at the standing robot's odometry point
        distance, direction = rng.uniform(1.0, 4.6), rng.uniform(1.5, 3.0)
        zx[i], zy[i] = 1.0 + distance * math.cos(direction), 2.0 + distance * math.sin(direction)
    fit = trimmed_rotation_fit(ox, oy, zx, zy, 4.0 * 0.03)
    assert fit is not None
    got, sigma, tx, ty, spread = fit
    assert abs(math.remainder(got - rotation, math.tau)) < 3.0 * sigma < 0.1
    assert math.hypot(tx - 1.0, ty - 2.0) < 0.03
    assert spread.residuals == 71 - 18  # every outlier trimmed, every good fix kept


def test_the_consensus_counts_points_so_a_still_start_does_not_hide_the_track() -> None:
    # most of a start-up window's fixes share the odometry point where the robot stood: every rotation explains them
    # alike, and the few fixes of the first metres of driving tell the rotations apart
    rng = np.random.default_rng(8)
    rotation = -2.0
    c, s = math.cos(rotation), math.sin(rotation)
    ox = [0.0] * 40 + [0.04 * i for i in range(1, 9)]
    oy = [0.0] * 48
    zx = [x * c - y * s + rng.normal(0.0, 0.02) for x, y in zip(ox, oy, strict=True)]
    zy = [x * s + y * c + rng.normal(0.0, 0.02) for x, y in zip(ox, oy, strict=True)]
    kept = heading.consensus(ox, oy, zx, zy, 4.0 * 0.02)
    assert set(range(40, 48)) <= set(kept)
    fit = trimmed_rotation_fit(ox, oy, zx, zy, 4.0 * 0.02, min_points=3)
    assert fit is not None
    assert abs(math.remainder(fit[0] - rotation, math.tau)) < 3.0 * fit[1]
