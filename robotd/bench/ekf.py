"""EKF predict + update against FilterPy's ExtendedKalmanFilter, and replay speed of a one-hour log."""

from __future__ import annotations

import math
import random
import time

from robotd import ekf, kinematics
from robotd.config import parse
from robotd.logfile import IpsFix, SensorLog, Wheels
from robotd.replay import replay

NAME = "ekf"


def _sequence(n: int) -> list[tuple[float, float, float, float, float, float]]:
    rng = random.Random(3)
    return [
        (rng.uniform(0, 0.5), rng.uniform(-0.2, 0.2), rng.uniform(-1, 1), 0.01, rng.gauss(0, 0.05), rng.gauss(0, 0.05))
        for _ in range(n)
    ]


def _robotd_steps(seq: list[tuple[float, float, float, float, float, float]]) -> float:
    noise = ekf.ControlNoise(lin2=4e-4, lat2=9e-4, slip2=2.5e-3, turn2=2.5e-3)
    x = y = th = 0.0
    p = ekf.cov_diag(1.0, 1.0, 0.1)
    r = 0.03**2
    start = time.perf_counter()
    for vx, vy, wz, dt, nx, ny in seq:
        q = ekf.process_noise(th, vx, vy, wz, dt, noise)
        x, y, th, p = ekf.predict(x, y, th, p, vx, vy, wz, dt, q)
        inn = ekf.innovation(x, y, th, p, x + nx, y + ny, r, 0.05, 0.0)
        x, y, th, p = ekf.update(x, y, th, p, inn, r)
    return time.perf_counter() - start


def _filterpy_steps(seq: list[tuple[float, float, float, float, float, float]]) -> float:
    import numpy as np  # noqa: PLC0415 - the baseline's imports stay out of robotd's import time
    from filterpy.kalman import ExtendedKalmanFilter  # noqa: PLC0415

    class Model(ExtendedKalmanFilter):  # type: ignore[misc]
        u = (0.0, 0.0, 0.0, 0.0)
        x: np.ndarray

        def predict_x(self, u: object = 0) -> None:  # noqa: ARG002 - FilterPy's signature; the control is self.u
            vx, vy, wz, dt = self.u
            th = float(self.x[2, 0])
            c, s = math.cos(th), math.sin(th)
            self.x = self.x + np.array([[(vx * c - vy * s) * dt], [(vx * s + vy * c) * dt], [wz * dt]])

    def hx(state: np.ndarray) -> np.ndarray:
        th = float(state[2, 0])
        return np.array([[state[0, 0] + 0.05 * math.cos(th)], [state[1, 0] + 0.05 * math.sin(th)]])

    def jacobian(state: np.ndarray) -> np.ndarray:
        th = float(state[2, 0])
        return np.array([[1.0, 0.0, -0.05 * math.sin(th)], [0.0, 1.0, 0.05 * math.cos(th)]])

    kf = Model(dim_x=3, dim_z=2)
    kf.P = np.diag([1.0, 1.0, 0.01])
    kf.R = np.eye(2) * 0.03**2
    start = time.perf_counter()
    for vx, vy, wz, dt, nx, ny in seq:
        th = float(kf.x[2, 0])
        c, s = math.cos(th), math.sin(th)
        kf.F = np.array([[1.0, 0.0, -(vx * s + vy * c) * dt], [0.0, 1.0, (vx * c - vy * s) * dt], [0.0, 0.0, 1.0]])
        g = np.array([[c * dt, -s * dt, 0.0], [s * dt, c * dt, 0.0], [0.0, 0.0, dt]])
        speed = math.hypot(vx, vy)
        kf.Q = g @ np.diag([4e-4 * speed / dt, 9e-4 * speed / dt, (2.5e-3 * speed + 2.5e-3 * abs(wz)) / dt]) @ g.T
        kf.u = (vx, vy, wz, dt)
        kf.predict()
        kf.update(np.array([[kf.x[0, 0] + nx], [kf.x[1, 0] + ny]]), jacobian, hx)
    return time.perf_counter() - start


def hour_log(seconds: float) -> SensorLog:
    """A log of `seconds` of 100 Hz wheel ticks (a slow circle) and 8 Hz fixes."""
    geometry = kinematics.Geometry()
    rng = random.Random(5)
    events: list[Wheels | IpsFix] = []
    wheel = kinematics.inverse(geometry, kinematics.Twist(0.3, 0.0, 0.1))
    x = y = th = 0.0
    for i in range(1, int(seconds * 100) + 1):
        t = i * 0.01
        ticks = tuple(int(w * t * 6800 / (2 * math.pi)) for w in wheel)
        events.append(Wheels(t, (ticks[0], ticks[1], ticks[2], ticks[3])))
        x, y, th = x + 0.3 * math.cos(th) * 0.01, y + 0.3 * math.sin(th) * 0.01, th + 0.001
        if i % 12 == 0:
            events.append(IpsFix(t + 0.05, x + rng.gauss(0, 0.03), y + rng.gauss(0, 0.03), 0.0, t))
    events.sort(key=lambda e: e.t)
    return SensorLog(events=list(events))


def run(quick: bool) -> dict[str, float]:
    """Time both filters on one sequence, and a replay of a long log; print the ratios."""
    seq = _sequence(2000 if quick else 20000)
    ours = min(_robotd_steps(seq) for _ in range(3))
    theirs = min(_filterpy_steps(seq) for _ in range(1 if quick else 2))
    per_ours, per_theirs = ours / len(seq) * 1e6, theirs / len(seq) * 1e6
    print(
        f"predict+update: robotd {per_ours:.1f} us, FilterPy {per_theirs:.1f} us, "
        f"ratio {ours / theirs:.3f} (target <= 0.333)"
    )
    seconds = 60.0 if quick else 3600.0
    log = hour_log(seconds)
    start = time.perf_counter()
    replay(log, parse(""))
    elapsed = time.perf_counter() - start
    speed = seconds / elapsed
    print(
        f"replay of {seconds:.0f} s (100 Hz wheels, 8 Hz fixes, already parsed): {elapsed:.2f} s, "
        f"{speed:.0f}x real time (target >= 2000)"
    )
    return {
        "robotd_step_us": per_ours,
        "filterpy_step_us": per_theirs,
        "step_ratio": ours / theirs,
        "replay_seconds": elapsed,
        "replay_x_real_time": speed,
    }
