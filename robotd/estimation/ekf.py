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
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple, TypeVar

import numpy as np
import numpy.typing as npt

Cov = tuple[float, float, float, float, float, float]
"""A symmetric 3x3 covariance as its upper triangle: (xx, xy, xt, yy, yt, tt)."""

TWO_PI = 2.0 * math.pi
Angle = TypeVar("Angle", float, npt.NDArray[np.float64])


def wrap_angle(angle: Angle) -> Angle:
    """The same angle in [-pi, pi): a float, or each element of an array."""
    wrapped: Angle = (angle + math.pi) % TWO_PI - math.pi
    return wrapped


def cov_full(p: Cov) -> tuple[float, float, float, float, float, float, float, float, float]:
    """The 3x3 covariance, row-major, from its upper triangle."""
    xx, xy, xt, yy, yt, tt = p
    return (xx, xy, xt, xy, yy, yt, xt, yt, tt)


def cov_diag(sx: float, sy: float, st: float) -> Cov:
    """A diagonal covariance from three standard deviations."""
    return (sx * sx, 0.0, 0.0, sy * sy, 0.0, st * st)


@dataclass(frozen=True, slots=True)
class ControlNoise:
    """Control noise M = diag(vx, vy, wz variances) per unit of time and of motion, mapped through G (Q = G M G^T).

    With speed = hypot(vx, vy), the variances added over one step are
    along-track position: lin2 * speed * dt (m^2), heading: (slip2 * speed + turn2 * |wz|) * dt (rad^2),
    plus a constant per-step (dt^2) term on the speeds, const_v2 and const_w2 (the paper's eq. 9).
    A robot at rest does not grow uncertain unless the per-step term says so.
    """

    lin2: float = 0.0
    lat2: float = 0.0
    slip2: float = 0.0
    turn2: float = 0.0
    const_v2: float = 0.0
    const_w2: float = 0.0


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
    dx, dy, c, s = displacement(vx, vy, wz, dt, theta, midpoint=midpoint)
    speed = math.hypot(vx, vy)
    inv_dt = 1.0 / dt
    # Variances of the control errors over this step; the random-walk terms grow with distance, not time,
    # so they enter M divided by dt (G carries dt twice).
    m_vx = noise.lin2 * speed * inv_dt + noise.const_v2
    m_vy = noise.lat2 * speed * inv_dt + noise.const_v2
    m_wz = (noise.slip2 * speed + noise.turn2 * abs(wz)) * inv_dt + noise.const_w2
    dt2 = dt * dt
    a = -dy  # eq. 6: d x'/d theta
    b = dx  # eq. 6: d y'/d theta
    cc, ss = c * c, s * s
    xx, xy, xt, yy, yt, tt = p
    p_new = (  # eq. 7, F P F^T written out for F = I + (a, b) in the theta column, plus Q (its theta cross terms are 0)
        xx + 2.0 * a * xt + a * a * tt + dt2 * (cc * m_vx + ss * m_vy),
        xy + a * yt + b * xt + a * b * tt + dt2 * c * s * (m_vx - m_vy),
        xt + a * tt,
        yy + 2.0 * b * yt + b * b * tt + dt2 * (ss * m_vx + cc * m_vy),
        yt + b * tt,
        tt + dt2 * m_wz,
    )
    return x + dx, y + dy, wrap_angle(theta + wz * dt), p_new


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
    det = s_xx * s_yy - s_xy * s_xy
    nis = (nu_x * nu_x * s_yy - 2.0 * nu_x * nu_y * s_xy + nu_y * nu_y * s_xx) / det
    return Innovation(nu_x, nu_y, s_xx, s_xy, s_yy, nis, h02, h12)


def update(  # noqa: PLR0917 - the paper's symbols as plain floats: no packing in the hot path
    x: float, y: float, theta: float, p: Cov, inn: Innovation, r: float, *, freeze_heading: bool = False
) -> tuple[float, float, float, Cov]:
    """Fuse an innovation (eqs. 12-17): Kalman gain, state correction, Joseph-form covariance.

    With freeze_heading the gain's heading row is zeroed (a fix taken at rest says nothing about the heading);
    the Joseph form keeps P exact for that sub-optimal gain.
    """
    xx, xy, xt, yy, yt, tt = p
    h02, h12 = inn.h02, inn.h12
    # P H^T, one column per measured axis
    u0x, u0y, u0t = xx + h02 * xt, xy + h02 * yt, xt + h02 * tt
    u1x, u1y, u1t = xy + h12 * xt, yy + h12 * yt, yt + h12 * tt
    det = inn.s_xx * inn.s_yy - inn.s_xy * inn.s_xy
    i00, i01, i11 = inn.s_yy / det, -inn.s_xy / det, inn.s_xx / det  # S^-1
    # eq. 13: K = P H^T S^-1 (3x2)
    k0x, k1x = u0x * i00 + u1x * i01, u0x * i01 + u1x * i11
    k0y, k1y = u0y * i00 + u1y * i01, u0y * i01 + u1y * i11
    k0t, k1t = (0.0, 0.0) if freeze_heading else (u0t * i00 + u1t * i01, u0t * i01 + u1t * i11)
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


def chi2_gate_2dof(probability: float) -> float:
    """The NIS threshold that a 2-dof chi-square variable stays below with this probability: -2 ln(1 - p)."""
    return -2.0 * math.log(1.0 - probability)


__all__ = [
    "ControlNoise",
    "Cov",
    "Innovation",
    "chi2_gate_2dof",
    "cov_diag",
    "cov_full",
    "displacement",
    "innovation",
    "predict",
    "update",
    "wrap_angle",
]
