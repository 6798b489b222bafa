"""The EKF of the paper (eqs. 3-17) as pure functions on plain floats: predict, process noise, IPS update.

State s = (x, y, theta) in the world frame, control u = (vx, vy, wz) in the body frame (paper eqs. 3-4).
The covariance P is symmetric, so it travels as its six upper-triangle entries (xx, xy, xt, yy, yt, tt): the
symmetry then holds by construction and a 3x3 step costs a few dozen float multiplications instead of a dozen
numpy calls (a 3x3 filter in numpy is all per-call overhead).

Process model, eq. 5 (an Euler step over dt, as the paper's dead reckoning eq. 2; robotd evaluates the heading at
the step's midpoint, theta + wz dt / 2, which keeps turns exact to second order):

    x' = x + (vx cos(theta) - vy sin(theta)) dt
    y' = y + (vx sin(theta) + vy cos(theta)) dt
    theta' = theta + wz dt

Its Jacobian with respect to the state, eq. 6, differs from the identity only in the theta column:

    F = [[1, 0, a], [0, 1, b], [0, 0, 1]],
    a = d x'/d theta = -(vx sin + vy cos) dt,  b = d y'/d theta = (vx cos - vy sin) dt

and with respect to the control, G = d f / d u = [[c dt, -s dt, 0], [s dt, c dt, 0], [0, 0, dt]], which maps a control
noise M (a covariance on vx, vy, wz) into the state: Q = G M G^T (the paper's eq. 9 writes a 2x2 Q on (v, w), which
does not fit the 3x3 covariance; this is the mapping that makes it fit).

Measurement model (the beacon at lever arm (ox, oy) in the body frame; the paper has ox = oy = 0):

    h(s) = (x + ox cos - oy sin, y + ox sin + oy cos),   H = [[1, 0, -ox sin - oy cos], [0, 1, ox cos - oy sin]]

Update, eqs. 10-17: innovation nu = z - h(s), S = H P H^T + R, K = P H^T S^-1, s += K nu (heading wrapped),
P = (I - K H) P (I - K H)^T + K R K^T (Joseph form: stays symmetric positive definite under rounding and for any K).

Odometry scales known only to within their calibration's uncertainty (Schmidt-Kalman "consider" parameters): the
odometry's relative scale errors e = (ex, ey, ew) on vx, vy, wz, of variances sigma_e = diag(v), are not estimated by
the filter (the calibration learns them) but their uncertainty is carried. A scale error is a bias, not noise: the
position error it makes grows with the distance driven, not its square root. The cross-covariance of the pose with e
is J diag(v), J = d pose / d e the pose's sensitivity to a scale error, with

    predict: J' = F J + B,  B = d f / d e = G diag(vx, vy, wz),
             P' = F P F^T + Q + F J Sigma B^T + B Sigma J^T F^T + B Sigma B^T
                = F P F^T + Q + sum_k v_k (n_k n_k^T - m_k m_k^T),  m_k = (F J)[:, k], n_k = J'[:, k]
    update:  J' = (I - K H) J  (P as above: P is the pose's whole covariance, the scales' share included)
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple, TypeVar

import numpy as np
import numpy.typing as npt

Cov = tuple[float, float, float, float, float, float]
"""A symmetric 3x3 covariance as its upper triangle: (xx, xy, xt, yy, yt, tt)."""
Sens = tuple[float, float, float, float, float, float, float, float, float]
"""d (x, y, theta) / d (relative scale errors of vx, vy, wz), row-major: the pose's sensitivity to odometry scales."""
NO_SENS: Sens = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
NO_SCALE_VAR = (0.0, 0.0, 0.0)  # odometry scales taken as exact: predict_considering is predict


def heading_sensitivity(sens: Sens) -> Sens:
    """sens with its position rows zero: a position that owes nothing to the odometry, its heading kept."""
    return (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, sens[6], sens[7], sens[8])


TWO_PI = 2.0 * math.pi
Angle = TypeVar("Angle", float, npt.NDArray[np.float64])


def wrap_angle(angle: Angle) -> Angle:
    """The same angle in [-pi, pi): a float, or each element of an array."""
    wrapped: Angle = (angle + math.pi) % TWO_PI - math.pi
    return wrapped


def cov_full(p: Sequence[float]) -> tuple[float, float, float, float, float, float, float, float, float]:
    """The 3x3 covariance, row-major, from its upper triangle (xx, xy, xt, yy, yt, tt)."""
    xx, xy, xt, yy, yt, tt = p
    return (xx, xy, xt, xy, yy, yt, xt, yt, tt)


def cov_diag(sx: float, sy: float, st: float) -> Cov:
    """A diagonal covariance from three standard deviations."""
    return (sx * sx, 0.0, 0.0, sy * sy, 0.0, st * st)


@dataclass(frozen=True, slots=True)
class ControlNoise:
    """Control noise M = diag(vx, vy, wz variances) per unit of time and of motion, mapped through G (Q = G M G^T).

    With speed = hypot(vx, vy), the variances added over one step are
    along-track position: lin2 * speed * dt (m^2), each position axis: spin2 * |wz| * dt (m^2, the centre of a robot
    turning moves by its wheels' unequal traction), heading: (slip2 * speed + turn2 * |wz|) * dt (rad^2),
    plus a constant per-step (dt^2) term on the speeds, const_v2 and const_w2 (the paper's eq. 9).
    A robot at rest does not grow uncertain unless the per-step term says so.
    """

    lin2: float = 0.0
    lat2: float = 0.0
    slip2: float = 0.0
    turn2: float = 0.0
    const_v2: float = 0.0
    const_w2: float = 0.0
    spin2: float = 0.0  # position variance per axis per radian turned (m^2/rad)


def displacement(
    vx: float, vy: float, wz: float, dt: float, theta: float, *, midpoint: bool
) -> tuple[float, float, float, float]:
    """A step's displacement (dx, dy) in the world from heading theta before it (eq. 5: at the midpoint heading
    theta + wz dt / 2, or at theta, the paper's Euler step), and the cosine and sine of the heading used."""
    th = theta + 0.5 * wz * dt if midpoint else theta
    c, s = math.cos(th), math.sin(th)
    return (vx * c - vy * s) * dt, (vx * s + vy * c) * dt, c, s


def predict(  # noqa: PLR0917 - the paper's symbols as plain floats: no packing in the hot path
    x: float,
    y: float,
    theta: float,
    p: Cov,
    vx: float,
    vy: float,
    wz: float,
    dt: float,
    noise: ControlNoise,
    *,
    midpoint: bool,
) -> tuple[float, float, float, Cov]:
    """One prediction step over dt > 0: the state through eq. 5 (see displacement) and P through eq. 7,
    P' = F P F^T + Q, with F from eq. 6 and Q = G M G^T the control noise of this motion (ControlNoise)."""
    x1, y1, theta1, p1, _ = predict_considering(
        x, y, theta, p, NO_SENS, vx, vy, wz, dt, noise, NO_SCALE_VAR, midpoint=midpoint
    )
    return x1, y1, theta1, p1


def predict_considering(  # noqa: PLR0917 - the paper's symbols as plain floats: no packing in the hot path
    x: float,
    y: float,
    theta: float,
    p: Cov,
    sens: Sens,
    vx: float,
    vy: float,
    wz: float,
    dt: float,
    noise: ControlNoise,
    scale_var: tuple[float, float, float],
    *,
    midpoint: bool,
) -> tuple[float, float, float, Cov, Sens]:
    """predict, with odometry scales uncertain by the relative variances scale_var (see the module docstring): the
    sensitivity J carried on, and P grown by the scales' share.

    One function for both (predict calls it with no uncertainty): the estimator's hot path, written out once.
    """
    th = theta + 0.5 * wz * dt if midpoint else theta  # displacement(), written out: the hot path's hottest call
    c, s = math.cos(th), math.sin(th)
    vxdt, vydt, wzdt = vx * dt, vy * dt, wz * dt
    dx, dy = vxdt * c - vydt * s, vxdt * s + vydt * c
    speed = math.hypot(vx, vy)
    # The control errors' variances over this step, times dt^2 (G carries dt twice): the random-walk terms grow with
    # distance, not time (speed dt), the paper's per-step terms with dt^2
    dt2 = dt * dt
    spin = noise.spin2 * abs(wz) * dt  # a robot turning on the spot moves its centre too
    q_vx = noise.lin2 * speed * dt + noise.const_v2 * dt2 + spin
    q_vy = noise.lat2 * speed * dt + noise.const_v2 * dt2 + spin
    q_wz = (noise.slip2 * speed + noise.turn2 * abs(wz)) * dt + noise.const_w2 * dt2
    a = -dy  # eq. 6: d x'/d theta
    b = dx  # eq. 6: d y'/d theta
    cc, ss = c * c, s * s
    xx, xy, xt, yy, yt, tt = p
    # eq. 7, F P F^T written out for F = I + (a, b) in the theta column, plus Q (its theta cross terms are 0)
    xx = xx + 2.0 * a * xt + a * a * tt + cc * q_vx + ss * q_vy
    xy = xy + a * yt + b * xt + a * b * tt + c * s * (q_vx - q_vy)
    xt = xt + a * tt
    yy = yy + 2.0 * b * yt + b * b * tt + ss * q_vx + cc * q_vy
    yt = yt + b * tt
    tt = tt + q_wz
    theta1 = (theta + wzdt + math.pi) % TWO_PI - math.pi  # wrap_angle, written out (the hot path)
    v0, v1, v2 = scale_var
    if v0 == 0.0 and v1 == 0.0 and v2 == 0.0:
        return x + dx, y + dy, theta1, (xx, xy, xt, yy, yt, tt), sens
    jx0, jx1, jx2, jy0, jy1, jy2, jt0, jt1, jt2 = sens
    # M = F J: F adds the heading row times (a, b) to the x and y rows
    mx0, mx1, mx2 = jx0 + a * jt0, jx1 + a * jt1, jx2 + a * jt2
    my0, my1, my2 = jy0 + b * jt0, jy1 + b * jt1, jy2 + b * jt2
    # J' = M + B; B's columns: (c, s, 0) vx dt, (-s, c, 0) vy dt, (0, 0, 1) wz dt
    bx0, by0 = c * vxdt, s * vxdt
    bx1, by1 = -s * vydt, c * vydt
    nx0, ny0, nx1, ny1, nt2 = mx0 + bx0, my0 + by0, mx1 + bx1, my1 + by1, jt2 + wzdt
    # sum_k v_k (n_k n_k^T - m_k m_k^T), upper triangle: B's column k differs from zero in the position rows for
    # k = 0, 1 and in the heading row for k = 2, so n_k and m_k share the other rows
    p_new = (
        xx + v0 * (nx0 * nx0 - mx0 * mx0) + v1 * (nx1 * nx1 - mx1 * mx1),
        xy + v0 * (nx0 * ny0 - mx0 * my0) + v1 * (nx1 * ny1 - mx1 * my1),
        xt + v0 * bx0 * jt0 + v1 * bx1 * jt1 + v2 * mx2 * wzdt,
        yy + v0 * (ny0 * ny0 - my0 * my0) + v1 * (ny1 * ny1 - my1 * my1),
        yt + v0 * by0 * jt0 + v1 * by1 * jt1 + v2 * my2 * wzdt,
        tt + v2 * (nt2 * nt2 - jt2 * jt2),
    )
    return x + dx, y + dy, theta1, p_new, (nx0, nx1, mx2, ny0, ny1, my2, jt0, jt1, nt2)


class Innovation(NamedTuple):
    """What an IPS fix says against the prediction: nu = z - h(s), S = H P H^T + R, NIS = nu^T S^-1 nu.

    A NamedTuple: as immutable as a frozen dataclass, and built several times faster (once or twice per fix).
    """

    nu_x: float
    nu_y: float
    s_xx: float
    s_xy: float
    s_yy: float
    nis: float
    h02: float
    h12: float


def innovation(  # noqa: PLR0917 - the paper's symbols as plain floats: no packing in the hot path
    x: float, y: float, theta: float, p: Cov, zx: float, zy: float, r: float, ox: float, oy: float
) -> Innovation:
    """The innovation of a fix z of the beacon at lever arm (ox, oy), with R = r I (eqs. 10-12)."""
    c, s = math.cos(theta), math.sin(theta)
    h02 = -ox * s - oy * c  # H's theta column
    h12 = ox * c - oy * s
    nu_x = zx - (x + ox * c - oy * s)  # eq. 10, with the lever arm
    nu_y = zy - (y + ox * s + oy * c)
    xx, xy, xt, yy, yt, tt = p
    s_xx = xx + 2.0 * h02 * xt + h02 * h02 * tt + r  # eq. 11, S = H P H^T + R
    s_xy = xy + h12 * xt + h02 * yt + h02 * h12 * tt
    s_yy = yy + 2.0 * h12 * yt + h12 * h12 * tt + r
    return Innovation(nu_x, nu_y, s_xx, s_xy, s_yy, mahalanobis2(nu_x, nu_y, s_xx, s_xy, s_yy), h02, h12)


def mahalanobis2(nu_x: float, nu_y: float, s_xx: float, s_xy: float, s_yy: float) -> float:
    """nu^T S^-1 nu for a 2-vector nu and a symmetric 2x2 S (the NIS of an innovation)."""
    det = s_xx * s_yy - s_xy * s_xy
    return (nu_x * nu_x * s_yy - 2.0 * nu_x * nu_y * s_xy + nu_y * nu_y * s_xx) / det


class Gain(NamedTuple):
    """The Kalman gain K = P H^T S^-1 (eq. 13), 3x2: the x, y and heading rows' columns for nu_x and nu_y."""

    k0x: float
    k1x: float
    k0y: float
    k1y: float
    k0t: float
    k1t: float


def gain(p: Cov, inn: Innovation, *, freeze_heading: bool = False) -> Gain:
    """The gain of an innovation (eq. 13); with freeze_heading its heading row is zero."""
    xx, xy, xt, yy, yt, tt = p
    h02, h12 = inn.h02, inn.h12
    # P H^T, one column per measured axis
    u0x, u0y, u0t = xx + h02 * xt, xy + h02 * yt, xt + h02 * tt
    u1x, u1y, u1t = xy + h12 * xt, yy + h12 * yt, yt + h12 * tt
    det = inn.s_xx * inn.s_yy - inn.s_xy * inn.s_xy
    i00, i01, i11 = inn.s_yy / det, -inn.s_xy / det, inn.s_xx / det  # S^-1
    k0t, k1t = (0.0, 0.0) if freeze_heading else (u0t * i00 + u1t * i01, u0t * i01 + u1t * i11)
    return Gain(u0x * i00 + u1x * i01, u0x * i01 + u1x * i11, u0y * i00 + u1y * i01, u0y * i01 + u1y * i11, k0t, k1t)


def update(  # noqa: PLR0917 - the paper's symbols as plain floats: no packing in the hot path
    x: float, y: float, theta: float, p: Cov, inn: Innovation, r: float, *, freeze_heading: bool = False
) -> tuple[float, float, float, Cov]:
    """Fuse an innovation (eqs. 12-17): Kalman gain, state correction, Joseph-form covariance.

    With freeze_heading the gain's heading row is zeroed (a fix taken at rest says nothing about the heading);
    the Joseph form keeps P exact for that sub-optimal gain.
    """
    return apply_gain(x, y, theta, p, inn, r, gain(p, inn, freeze_heading=freeze_heading))


def apply_gain(  # noqa: PLR0917 - the paper's symbols as plain floats: no packing in the hot path
    x: float, y: float, theta: float, p: Cov, inn: Innovation, r: float, k: Gain
) -> tuple[float, float, float, Cov]:
    """The state corrected by gain k (eq. 14) and its Joseph-form covariance (eqs. 15-17)."""
    xx, xy, xt, yy, yt, tt = p
    h02, h12 = inn.h02, inn.h12
    k0x, k1x, k0y, k1y, k0t, k1t = k
    nu_x, nu_y = inn.nu_x, inn.nu_y
    x_new = x + k0x * nu_x + k1x * nu_y  # eq. 14
    y_new = y + k0y * nu_x + k1y * nu_y
    theta_new = wrap_angle(theta + k0t * nu_x + k1t * nu_y)
    # eq. 15-17, Joseph form: A = I - K H, P' = A P A^T + K R K^T
    a00, a01, a02 = 1.0 - k0x, -k1x, -(k0x * h02 + k1x * h12)
    a10, a11, a12 = -k0y, 1.0 - k1y, -(k0y * h02 + k1y * h12)
    a20, a21, a22 = -k0t, -k1t, 1.0 - (k0t * h02 + k1t * h12)
    m00, m01, m02 = a00 * xx + a01 * xy + a02 * xt, a00 * xy + a01 * yy + a02 * yt, a00 * xt + a01 * yt + a02 * tt
    m10, m11, m12 = a10 * xx + a11 * xy + a12 * xt, a10 * xy + a11 * yy + a12 * yt, a10 * xt + a11 * yt + a12 * tt
    m20, m21, m22 = a20 * xx + a21 * xy + a22 * xt, a20 * xy + a21 * yy + a22 * yt, a20 * xt + a21 * yt + a22 * tt
    p_new = (
        m00 * a00 + m01 * a01 + m02 * a02 + r * (k0x * k0x + k1x * k1x),
        m00 * a10 + m01 * a11 + m02 * a12 + r * (k0x * k0y + k1x * k1y),
        m00 * a20 + m01 * a21 + m02 * a22 + r * (k0x * k0t + k1x * k1t),
        m10 * a10 + m11 * a11 + m12 * a12 + r * (k0y * k0y + k1y * k1y),
        m10 * a20 + m11 * a21 + m12 * a22 + r * (k0y * k0t + k1y * k1t),
        m20 * a20 + m21 * a21 + m22 * a22 + r * (k0t * k0t + k1t * k1t),
    )
    return x_new, y_new, theta_new, p_new


def corrected_sensitivity(sens: Sens, inn: Innovation, k: Gain) -> Sens:
    """The pose's sensitivity to the odometry scales after a fix fused with gain k: (I - K H) J."""
    h02, h12 = inn.h02, inn.h12
    k0x, k1x, k0y, k1y, k0t, k1t = k
    jx0, jx1, jx2, jy0, jy1, jy2, jt0, jt1, jt2 = sens
    # (K H) J, row i: K[i] . (J_x + h02 J_t, J_y + h12 J_t)
    hx0, hx1, hx2 = jx0 + h02 * jt0, jx1 + h02 * jt1, jx2 + h02 * jt2
    hy0, hy1, hy2 = jy0 + h12 * jt0, jy1 + h12 * jt1, jy2 + h12 * jt2
    return (
        jx0 - k0x * hx0 - k1x * hy0,
        jx1 - k0x * hx1 - k1x * hy1,
        jx2 - k0x * hx2 - k1x * hy2,
        jy0 - k0y * hx0 - k1y * hy0,
        jy1 - k0y * hx1 - k1y * hy1,
        jy2 - k0y * hx2 - k1y * hy2,
        jt0 - k0t * hx0 - k1t * hy0,
        jt1 - k0t * hx1 - k1t * hy1,
        jt2 - k0t * hx2 - k1t * hy2,
    )


def sensitivity_for_scale_var(sens: Sens, old: tuple[float, float, float], new: tuple[float, float, float]) -> Sens:
    """The sensitivity to carry on when the scales' relative variances change from `old` to `new`: a column whose
    variance grew is shrunk by sqrt(old / new), so the scales' share of P, sum v_k j_k j_k^T, stays what it is.

    predict_considering takes that share out of P with the variance in use (the m_k m_k^T terms); with a grown
    variance and the old sensitivity it took out more than P held, and P lost its positive definiteness (a calibration
    window that judged its fixes too few to move the odometry put the scales back on their prior: 1.7 % -> 10 %, and
    a spin of 0.35 rad turned the heading's variance negative). The pose's error owed to the scales so far is kept;
    from now on it grows with the larger variance. A variance that shrank leaves the column as it is (less is taken
    out of P than it holds)."""
    factors = sensitivity_factors(old, new)
    return sens if factors is None else shrink_sensitivity(sens, factors)


def sensitivity_factors(
    old: tuple[float, float, float], new: tuple[float, float, float]
) -> tuple[float, float, float] | None:
    """Each column's factor of sensitivity_for_scale_var, sqrt(old / new) where the variance grew, else 1; None when
    none grew."""
    if all(n <= o for o, n in zip(old, new, strict=True)):
        return None
    f0, f1, f2 = (math.sqrt(o / n) if n > o else 1.0 for o, n in zip(old, new, strict=True))
    return f0, f1, f2


def shrink_sensitivity(sens: Sens, factors: tuple[float, float, float]) -> Sens:
    """The sensitivity with its column k multiplied by factors[k]."""
    f0, f1, f2 = factors
    jx0, jx1, jx2, jy0, jy1, jy2, jt0, jt1, jt2 = sens
    return (jx0 * f0, jx1 * f1, jx2 * f2, jy0 * f0, jy1 * f1, jy2 * f2, jt0 * f0, jt1 * f1, jt2 * f2)


def chi2_gate_2dof(probability: float) -> float:
    """The NIS threshold that a 2-dof chi-square variable stays below with this probability: -2 ln(1 - p)."""
    return -2.0 * math.log(1.0 - probability)


__all__ = [
    "NO_SCALE_VAR",
    "NO_SENS",
    "ControlNoise",
    "Cov",
    "Gain",
    "Innovation",
    "Sens",
    "apply_gain",
    "chi2_gate_2dof",
    "corrected_sensitivity",
    "cov_diag",
    "cov_full",
    "displacement",
    "gain",
    "heading_sensitivity",
    "innovation",
    "mahalanobis2",
    "predict",
    "predict_considering",
    "sensitivity_factors",
    "sensitivity_for_scale_var",
    "shrink_sensitivity",
    "update",
    "wrap_angle",
]
