"""The EKF's maths: step by step equal to FilterPy's ExtendedKalmanFilter, covariance symmetric positive definite."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest
from filterpy.kalman import ExtendedKalmanFilter
from hypothesis import given, settings
from hypothesis import strategies as st

from robotd import kinematics
from robotd.estimation import ekf


class _ModelEKF(ExtendedKalmanFilter):  # type: ignore[misc]
    """FilterPy's EKF with the paper's nonlinear process model (eq. 5) in place of its linear x = F x + B u."""

    x: np.ndarray

    def __init__(self) -> None:
        super().__init__(dim_x=3, dim_z=2)
        self.u = (0.0, 0.0, 0.0, 0.0)

    def predict_x(self, u: object = 0) -> None:
        vx, vy, wz, dt = self.u
        x, y, th = (float(v) for v in self.x.ravel())
        c, s = math.cos(th), math.sin(th)
        self.x = np.array([[x + (vx * c - vy * s) * dt], [y + (vx * s + vy * c) * dt], [th + wz * dt]])


def _random_cov(rng: random.Random) -> ekf.Cov:
    a = np.array([[rng.gauss(0, 0.5) for _ in range(3)] for _ in range(3)])
    m = a @ a.T + np.diag([1e-4, 1e-4, 1e-5])
    return (m[0, 0], m[0, 1], m[0, 2], m[1, 1], m[1, 2], m[2, 2])


def _full(p: ekf.Cov) -> np.ndarray:
    return np.array(ekf.cov_full(p)).reshape(3, 3)


def _control_noise(noise: ekf.ControlNoise, th: float, vx: float, vy: float, wz: float, dt: float) -> np.ndarray:
    """Q = G M G^T as design.md states it: M the control noise of this motion, G = d f / d u at heading th."""
    speed = math.hypot(vx, vy)
    m = np.diag(
        [
            noise.lin2 * speed / dt + noise.const_v2,
            noise.lat2 * speed / dt + noise.const_v2,
            (noise.slip2 * speed + noise.turn2 * abs(wz)) / dt + noise.const_w2,
        ]
    )
    c, s = math.cos(th), math.sin(th)
    g = np.array([[c * dt, -s * dt, 0.0], [s * dt, c * dt, 0.0], [0.0, 0.0, dt]])
    return np.asarray(g @ m @ g.T)


def test_predict_and_update_equal_filterpy_step_by_step() -> None:
    rng = random.Random(7)
    x, y, th = 0.3, -0.2, 0.4
    p = _random_cov(rng)
    ref = _ModelEKF()
    noise = ekf.ControlNoise(lin2=4e-4, lat2=9e-4, slip2=2.5e-3, turn2=2.5e-3, const_v2=0.01, const_w2=0.02)
    for step in range(3000):
        if step % 200 == 0:  # start again from a random state so that every part of the state space is visited
            x, y, th, p = rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(-3, 3), _random_cov(rng)
        ref.x = np.array([[x], [y], [th]])
        ref.P = _full(p)
        vx, vy, wz, dt = rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(-2, 2), rng.uniform(0.001, 0.2)
        c, s = math.cos(th), math.sin(th)
        ref.F = np.array([[1, 0, -(vx * s + vy * c) * dt], [0, 1, (vx * c - vy * s) * dt], [0, 0, 1]])
        ref.Q = _control_noise(noise, th, vx, vy, wz, dt)
        ref.u = (vx, vy, wz, dt)
        ref.predict()
        x, y, th, p = ekf.predict(x, y, th, p, vx, vy, wz, dt, noise, midpoint=False)
        assert np.allclose([x, y], ref.x.ravel()[:2], rtol=0, atol=1e-9)
        assert abs(ekf.wrap_angle(th - float(ref.x[2, 0]))) < 1e-9
        assert np.allclose(_full(p), ref.P, rtol=0, atol=1e-9)
        ox, oy = rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2)
        r = rng.uniform(0.0005, 0.05)
        zx, zy = x + rng.gauss(0, 0.3), y + rng.gauss(0, 0.3)

        def hx(state: np.ndarray, ox: float = ox, oy: float = oy) -> np.ndarray:
            t = float(state[2, 0])
            return np.array(
                [
                    [state[0, 0] + ox * math.cos(t) - oy * math.sin(t)],
                    [state[1, 0] + ox * math.sin(t) + oy * math.cos(t)],
                ]
            )

        def jacobian(state: np.ndarray, ox: float = ox, oy: float = oy) -> np.ndarray:
            t = float(state[2, 0])
            return np.array([[1, 0, -ox * math.sin(t) - oy * math.cos(t)], [0, 1, ox * math.cos(t) - oy * math.sin(t)]])

        ref.x = np.array([[x], [y], [th]])
        ref.R = np.eye(2) * r
        ref.update(np.array([[zx], [zy]]), jacobian, hx)
        inn = ekf.innovation(x, y, th, p, zx, zy, r, ox, oy)
        assert np.allclose([inn.nu_x, inn.nu_y], ref.y.ravel(), rtol=0, atol=1e-9)
        assert np.allclose([[inn.s_xx, inn.s_xy], [inn.s_xy, inn.s_yy]], ref.S, rtol=0, atol=1e-9)
        x, y, th, p = ekf.update(x, y, th, p, inn, r)
        assert np.allclose([x, y], ref.x.ravel()[:2], rtol=0, atol=1e-9)
        assert abs(ekf.wrap_angle(th - float(ref.x[2, 0]))) < 1e-9
        assert np.allclose(_full(p), ref.P, rtol=0, atol=1e-9)


def test_nis_is_the_mahalanobis_distance() -> None:
    p = (0.04, 0.01, 0.0, 0.09, 0.0, 0.01)
    inn = ekf.innovation(0.0, 0.0, 0.0, p, 0.3, -0.2, 0.01, 0.0, 0.0)
    s = np.array([[inn.s_xx, inn.s_xy], [inn.s_xy, inn.s_yy]])
    nu = np.array([0.3, -0.2])
    assert math.isclose(inn.nis, float(nu @ np.linalg.solve(s, nu)), rel_tol=1e-12)


def test_chi2_gate_matches_the_2dof_quantile() -> None:
    # the 2-dof chi-square CDF is 1 - exp(-d/2): its 99.9 % quantile is 13.8155
    assert math.isclose(ekf.chi2_gate_2dof(0.999), 13.815510557964274, rel_tol=1e-12)
    assert math.isclose(1.0 - math.exp(-ekf.chi2_gate_2dof(0.95) / 2.0), 0.95, rel_tol=1e-12)


finite = st.floats(-2.0, 2.0, allow_nan=False)


@settings(max_examples=60, deadline=None)
@given(
    steps=st.lists(
        st.tuples(finite, finite, finite, st.floats(0.001, 0.5), st.booleans(), finite, finite, st.floats(1e-4, 1.0)),
        min_size=1,
        max_size=40,
    ),
    frozen=st.booleans(),
)
def test_covariance_stays_symmetric_positive_definite(
    steps: list[tuple[float, float, float, float, bool, float, float, float]], frozen: bool
) -> None:
    x = y = th = 0.0
    p = ekf.cov_diag(1.0, 1.0, 0.5)
    noise = ekf.ControlNoise(lin2=4e-4, lat2=9e-4, slip2=2.5e-3, turn2=2.5e-3)
    for vx, vy, wz, dt, fix, zx, zy, r in steps:
        x, y, th, p = ekf.predict(x, y, th, p, vx, vy, wz, dt, noise, midpoint=True)
        if fix:
            inn = ekf.innovation(x, y, th, p, zx, zy, r * r, 0.1, -0.05)
            x, y, th, p = ekf.update(x, y, th, p, inn, r * r, freeze_heading=frozen)
        eigenvalues = np.linalg.eigvalsh(_full(p))
        assert eigenvalues.min() > 0.0
        assert -math.pi <= th < math.pi


@given(vx=st.floats(-2, 2), vy=st.floats(-2, 2), wz=st.floats(-5, 5), r=st.floats(0.01, 0.2), half=st.floats(0.05, 0.5))
def test_inverse_kinematics_round_trips_the_forward_kinematics(
    vx: float, vy: float, wz: float, r: float, half: float
) -> None:
    geometry = kinematics.Geometry(r, half, half * 0.9)
    twist = kinematics.forward(geometry, kinematics.inverse(geometry, kinematics.Twist(vx, vy, wz)))
    assert math.isclose(twist.vx, vx, abs_tol=1e-9)
    assert math.isclose(twist.vy, vy, abs_tol=1e-9)
    assert math.isclose(twist.wz, wz, abs_tol=1e-9)


def test_frozen_heading_leaves_theta_alone() -> None:
    p = (0.01, 0.0, 0.005, 0.01, 0.002, 0.05)
    inn = ekf.innovation(0.0, 0.0, 0.3, p, 0.2, 0.1, 0.001, 0.0, 0.0)
    _, _, th, _ = ekf.update(0.0, 0.0, 0.3, p, inn, 0.001, freeze_heading=True)
    _, _, th_free, _ = ekf.update(0.0, 0.0, 0.3, p, inn, 0.001)
    assert math.isclose(th, 0.3, abs_tol=1e-12)
    assert th_free != 0.3


def test_the_midpoint_step_is_the_euler_step_at_the_midpoint_heading() -> None:
    noise = ekf.ControlNoise(lin2=4e-4, lat2=9e-4, slip2=2.5e-3, turn2=2.5e-3)
    rng = random.Random(5)
    for _ in range(200):
        x, y, th, p = rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(-3, 3), _random_cov(rng)
        vx, vy, wz, dt = rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(-2, 2), rng.uniform(0.001, 0.2)
        mx, my, mth, _ = ekf.predict(x, y, th, p, vx, vy, wz, dt, noise, midpoint=True)
        mid = th + 0.5 * wz * dt
        ex, ey, _, _ = ekf.predict(x, y, mid, p, vx, vy, wz, dt, noise, midpoint=False)
        assert (mx, my) == (ex, ey)
        assert mth == ekf.wrap_angle(th + wz * dt)


def test_angles_wrap_the_same_as_floats_and_as_arrays() -> None:
    angles = [-7.0, -math.pi, -0.5, 0.0, math.pi, 3 * math.pi + 0.25, 100.0]
    wrapped = ekf.wrap_angle(np.array(angles))
    for angle, w in zip(angles, wrapped, strict=True):
        assert ekf.wrap_angle(angle) == w
        assert -math.pi <= w < math.pi
        assert math.isclose(math.cos(w), math.cos(angle), abs_tol=1e-12)
        assert math.isclose(math.sin(w), math.sin(angle), abs_tol=1e-12)


def _augmented_step(state: np.ndarray, u: tuple[float, float, float], dt: float) -> np.ndarray:
    """Eq. 5 (Euler) on the state augmented with relative scale errors of vx, vy and wz, which stay constant."""
    x, y, th, ex, ey, ew = state
    vx, vy, wz = u[0] * (1.0 + ex), u[1] * (1.0 + ey), u[2] * (1.0 + ew)
    c, s = math.cos(th), math.sin(th)
    return np.array([x + (vx * c - vy * s) * dt, y + (vx * s + vy * c) * dt, th + wz * dt, ex, ey, ew])


def test_the_odometry_scales_share_is_the_augmented_schmidt_filter_s() -> None:
    # the reference: the 6-state filter of pose and scale errors, its Jacobian by finite differences, and the
    # Schmidt-Kalman update (the scale errors are considered, not estimated: their rows of the gain are zero)
    rng = random.Random(5)
    noise = ekf.ControlNoise(lin2=4e-4, lat2=9e-4, slip2=2.5e-3, turn2=2.5e-3, const_v2=1e-4, const_w2=1e-4)
    scale_var = (0.01, 0.02, 0.015)
    x, y, th, p, sens = 0.0, 0.0, 0.3, ekf.cov_diag(0.1, 0.2, 0.05), ekf.NO_SENS
    aug = np.zeros((6, 6))
    aug[:3, :3] = np.reshape(ekf.cov_full(p), (3, 3))
    aug[3:, 3:] = np.diag(scale_var)
    r = 0.01
    for step in range(200):
        u = (rng.uniform(-0.5, 0.5), rng.uniform(-0.3, 0.3), rng.uniform(-1.0, 1.0))
        dt = 0.02
        here = np.array([x, y, th, 0.0, 0.0, 0.0])
        jac = np.zeros((6, 6))
        for k in range(6):
            d = np.zeros(6)
            d[k] = 1e-7
            jac[:, k] = (_augmented_step(here + d, u, dt) - _augmented_step(here - d, u, dt)) / 2e-7
        q = np.zeros((6, 6))
        step_noise = ekf.predict(x, y, th, (0.0,) * 6, *u, dt, noise, midpoint=False)[3]
        q[:3, :3] = np.reshape(ekf.cov_full(step_noise), (3, 3))
        aug = jac @ aug @ jac.T + q
        x, y, th, p, sens = ekf.predict_considering(x, y, th, p, sens, *u, dt, noise, scale_var, midpoint=False)
        if step % 10 == 9:
            inn = ekf.innovation(x, y, th, p, x + rng.gauss(0, 0.1), y + rng.gauss(0, 0.1), r, 0.1, 0.05)
            kg = ekf.gain(p, inn)
            sens = ekf.corrected_sensitivity(sens, inn, kg)
            x, y, th, p = ekf.apply_gain(x, y, th, p, inn, r, kg)
            h = np.array([[1.0, 0.0, inn.h02, 0.0, 0.0, 0.0], [0.0, 1.0, inn.h12, 0.0, 0.0, 0.0]])
            gain = np.zeros((6, 2))
            gain[:3] = [[kg.k0x, kg.k1x], [kg.k0y, kg.k1y], [kg.k0t, kg.k1t]]
            a = np.eye(6) - gain @ h
            aug = a @ aug @ a.T + r * gain @ gain.T
    assert np.reshape(ekf.cov_full(p), (3, 3)) == pytest.approx(aug[:3, :3], abs=1e-9)
    assert np.reshape(sens, (3, 3)) @ np.diag(scale_var) == pytest.approx(aug[:3, 3:], abs=1e-9)
    assert float(np.abs(aug[:3, 3:]).max()) > 1e-4  # the pose does depend on the scales: the check has teeth


def test_turning_on_the_spot_grows_the_position_by_its_own_term_per_radian_only() -> None:
    p: ekf.Cov = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    noise = ekf.ControlNoise(lin2=4e-4, lat2=9e-4, turn2=2.5e-3, spin2=1e-5)
    turned = 0.0
    x = y = th = 0.0
    for _ in range(50):  # half a turn on the spot at 1.57 rad/s, 20 ms steps
        x, y, th, p = ekf.predict(x, y, th, p, 0.0, 0.0, math.pi / 2, 0.02, noise, midpoint=True)
        turned += math.pi / 2 * 0.02
    assert (x, y) == (0.0, 0.0)
    assert p[0] == pytest.approx(1e-5 * turned)
    assert p[3] == pytest.approx(1e-5 * turned)
    assert p[1] == pytest.approx(0.0, abs=1e-15)  # as much along every axis
    exact = ekf.predict(0.0, 0.0, 0.0, (0.0,) * 6, 0.0, 0.0, 1.0, 0.02, ekf.ControlNoise(turn2=2.5e-3), midpoint=True)
    assert exact[3][0] == 0.0  # without the term a turn on the spot leaves the position exact


def _smallest_eigenvalue(p: ekf.Cov) -> float:
    return float(np.linalg.eigvalsh(np.reshape(ekf.cov_full(p), (3, 3))).min())


def test_a_scale_variance_that_grows_leaves_the_covariance_positive_definite() -> None:
    # turns made while the rotation scale was well known (1.7 %), then the scale's uncertainty put back on its 10 %
    # prior (a calibration window that could not move the odometry), then a spin the other way
    noise = ekf.ControlNoise(lin2=4e-4, lat2=9e-4, turn2=2.5e-3)
    known, prior = (0.017**2,) * 3, (0.1**2,) * 3
    x, y, th, p, sens = 0.0, 0.0, 0.0, ekf.cov_diag(0.05, 0.05, 0.05), ekf.NO_SENS
    for _ in range(200):  # 4 s of driving in circles at 3 rad/s
        x, y, th, p, sens = ekf.predict_considering(x, y, th, p, sens, 0.3, 0.0, 3.0, 0.02, noise, known, midpoint=True)

    def spun(sens: ekf.Sens) -> ekf.Cov:
        return ekf.predict_considering(x, y, th, p, sens, 0.3, 0.0, -3.0, 0.12, noise, prior, midpoint=True)[3]

    assert _smallest_eigenvalue(spun(sens)) < 0.0  # the old sensitivity with the grown variance: not a covariance
    rescaled = ekf.sensitivity_for_scale_var(sens, known, prior)
    assert _smallest_eigenvalue(spun(rescaled)) > 0.0
    # the scales' share of P is kept: sum v_k j_k j_k^T the same with the new variances and sensitivity
    share = np.reshape(sens, (3, 3)) @ np.diag(known) @ np.reshape(sens, (3, 3)).T
    kept = np.reshape(rescaled, (3, 3)) @ np.diag(prior) @ np.reshape(rescaled, (3, 3)).T
    assert kept == pytest.approx(share, rel=1e-12, abs=1e-18)
    assert ekf.sensitivity_for_scale_var(sens, prior, known) == sens  # a variance that shrank changes nothing
