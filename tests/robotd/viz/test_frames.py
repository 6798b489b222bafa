"""Planar frames: composition and inverse, the filter's correction, the 95 % ellipse, the 6x6 covariance."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from robotd.viz import frames

coordinate = st.floats(-100.0, 100.0)
angle = st.floats(-math.pi, math.pi)
pose = st.tuples(coordinate, coordinate, angle)


@given(pose, pose)
def test_the_correction_carries_the_odometry_pose_onto_the_fused_one(fused: frames.Pose2, odom: frames.Pose2) -> None:
    x, y, th = frames.compose(frames.correction(fused, odom), odom)
    assert x == pytest.approx(fused[0], abs=1e-9)
    assert y == pytest.approx(fused[1], abs=1e-9)
    assert math.remainder(th - fused[2], math.tau) == pytest.approx(0.0, abs=1e-9)


def test_compose_turns_the_child_frame_by_the_parents_heading() -> None:
    x, y, th = frames.compose((1.0, 2.0, math.pi / 2), (1.0, 0.0, 0.0))
    assert (x, y, th) == pytest.approx((1.0, 3.0, math.pi / 2))


def test_the_95_percent_ellipse_of_an_axis_aligned_covariance_has_the_chi_square_radii() -> None:
    cov = [4.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.1]
    outline = frames.covariance_ellipse((10.0, 20.0), cov)
    assert outline[0] == outline[-1]
    radius = math.sqrt(5.991464547107979)
    assert max(x for x, _ in outline) - 10.0 == pytest.approx(2.0 * radius)
    assert max(y for _, y in outline) - 20.0 == pytest.approx(1.0 * radius, rel=1e-2)


def test_a_correlated_covariance_tilts_the_ellipse_along_the_correlation() -> None:
    outline = frames.covariance_ellipse((0.0, 0.0), [1.0, 0.9, 0.0, 0.9, 1.0, 0.0, 0.0, 0.0, 0.0])
    far = max(outline, key=lambda p: math.hypot(*p))
    assert (
        abs(abs(math.atan2(far[1], far[0])) - math.pi / 4) < 0.1
        or abs(abs(math.atan2(far[1], far[0])) - 3 * math.pi / 4) < 0.1
    )


def test_a_degenerate_covariance_draws_a_point_rather_than_failing() -> None:
    assert set(frames.covariance_ellipse((1.0, 1.0), [0.0] * 9)) == {(1.0, 1.0)}


def test_the_planar_covariance_lands_on_x_y_and_yaw_of_the_6x6() -> None:
    cov6 = frames.covariance_6x6([1.0, 2.0, 3.0, 2.0, 5.0, 6.0, 3.0, 6.0, 9.0])
    assert cov6[0] == 1.0
    assert cov6[1] == 2.0
    assert cov6[5] == 3.0
    assert cov6[6 * 5 + 5] == 9.0
    assert cov6[6 * 1 + 5] == 6.0
    assert cov6[6 * 2 + 2] == 0.0
    assert sum(cov6) == 1 + 2 + 3 + 2 + 5 + 6 + 3 + 6 + 9
