"""EKF predict + update against FilterPy's EKF, and `robotd replay` of one-hour logs against real time (target 500x)."""

from __future__ import annotations

import contextlib
import dataclasses
import io
import math
import random
import tempfile
import time
from pathlib import Path

from robotd import cli
from robotd.config.model import load, parse
from robotd.estimation import ekf
from robotd.estimation.wheelsteps import TickKinematics
from robotd.logs.sensorlog import LogWriter, Truth, TwistSample, Wheels, read_log
from robotd.offline.replay import replay, write_outputs
from robotd.sim.offline import meta_for
from robotd.sim.offline import run as run_offline
from robotd.sim.scenarios import build as build_scenario
from robotd.sim.world import geometry_of, scenario_params

NAME = "ekf"
CONFIG = Path(__file__).resolve().parents[2] / "config" / "sim.yaml"
TARGET_X_REAL_TIME = 500  # issue 13: the daemon's estimator, event by event, replays an hour in under 7.2 s


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
    for (
        vx,
        vy,
        wz,
        dt,
        nx,
        ny,
    ) in seq:  # the calls the estimator makes (robotd.estimation.history.Predictor, Estimator.on_fix)
        x, y, th, p = ekf.predict(x, y, th, p, vx, vy, wz, dt, noise, midpoint=True)
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


def write_hour_logs(folder: Path, loops: int) -> tuple[float, dict[str, Path]]:
    """Simulate the virtual robot driving `loops` of the paper's square (44 s each; 100 Hz wheels and truth, 8 Hz
    fixes with outliers, dropouts and outages) and write it three ways: "replay" without truth, "replay_truth" with
    it, "replay_twists" without truth and each wheel sample as the twist of its ticks; returns the duration and the
    paths."""
    base = load(CONFIG)
    config = dataclasses.replace(
        base,
        encoders=dataclasses.replace(base.encoders, publish_rate_hz=100.0),
        sim=dataclasses.replace(base.sim, ips_rate_hz=8.0),
    )
    scenario = build_scenario("square", scenario_params(config.sim), loops, config.sim.seed)
    meta = meta_for(config, f"robotd bench ekf: simulate square --loops {loops}")
    kinematics = TickKinematics(geometry_of(config), config.encoders.counts_per_rev)
    paths = {key: folder / f"{key}.jsonl" for key in ("replay", "replay_truth", "replay_twists")}
    previous: Wheels | None = None
    first = last = 0.0
    with contextlib.ExitStack() as files:
        plain, truth, twists = (
            LogWriter(files.enter_context(open(path, "w", encoding="utf-8")), meta) for path in paths.values()
        )
        for event in run_offline(config, scenario, config.sim.seed):
            last = event.t
            truth.write(event)
            if isinstance(event, Truth):
                continue
            plain.write(event)
            if isinstance(event, Wheels):
                if previous is not None:
                    twists.write(
                        TwistSample(event.t, *kinematics.twist(previous.ticks, event.ticks, event.t - previous.t))
                    )
                else:
                    first = event.t
                previous = event
                continue
            twists.write(event)
    return last - first, paths


def _replay_stages(log_path: Path, out: Path, runs: int) -> tuple[float, float, float]:
    """Seconds spent reading, replaying and writing, each on its own (to see where the time goes): the run of `runs`
    that took the least in all, so that its stages are one run's, as the end-to-end figure is its best run's."""
    best = (math.inf, math.inf, math.inf)
    for _ in range(runs):
        start = time.perf_counter()
        log = read_log(log_path)
        read = time.perf_counter()
        result = replay(log, parse(""))
        replayed = time.perf_counter()
        write_outputs(result, out)
        stages = (read - start, replayed - read, time.perf_counter() - replayed)
        if sum(stages) < sum(best):
            best = stages
    return best


def _replay_seconds(log_path: Path, out: Path, runs: int) -> float:
    """The best of `runs` end-to-end `robotd replay` runs (the machine is shared)."""
    elapsed = math.inf
    for _ in range(runs):
        start = time.perf_counter()
        with contextlib.redirect_stdout(io.StringIO()):
            status = cli.main(["replay", str(log_path), "--out", str(out)])
        elapsed = min(elapsed, time.perf_counter() - start)
        if status != 0:
            raise RuntimeError(f"robotd replay failed with status {status}")
    return elapsed


def run(quick: bool) -> dict[str, float]:
    """Time both filters on one sequence, and `robotd replay` of a one-hour log of the virtual robot end to end,
    without truth (the target: robotd's filter alone), with truth (four methods scored) and with twists; print the
    ratios."""
    seq = _sequence(2000 if quick else 20000)
    ours = min(_robotd_steps(seq) for _ in range(3))
    theirs = min(_filterpy_steps(seq) for _ in range(1 if quick else 2))
    per_ours, per_theirs = ours / len(seq) * 1e6, theirs / len(seq) * 1e6
    print(
        f"predict+update: robotd {per_ours:.1f} us, FilterPy {per_theirs:.1f} us, "
        f"ratio {ours / theirs:.3f} (target <= 0.333)"
    )
    loops, runs = (2, 1) if quick else (82, 3)
    figures: dict[str, float] = {
        "robotd_step_us": per_ours,
        "filterpy_step_us": per_theirs,
        "step_ratio": ours / theirs,
    }
    with tempfile.TemporaryDirectory(prefix="robotd-bench-ekf-") as folder:
        seconds, paths = write_hour_logs(Path(folder), loops)
        for key, what in (
            ("replay", "100 Hz wheels, 8 Hz fixes, no truth; read, robotd's filter, outputs"),
            ("replay_truth", "100 Hz wheels, 8 Hz fixes, 100 Hz truth; read, 4 methods, metrics, outputs"),
            ("replay_twists", "100 Hz twists instead of wheels, 8 Hz fixes, no truth"),
        ):
            out = Path(folder) / "out"
            elapsed = _replay_seconds(paths[key], out, runs)
            stages = _replay_stages(paths[key], out, runs)
            apart = "one more run" if runs == 1 else f"the best of {runs} more runs"
            speed = seconds / elapsed
            target = f" (target >= {TARGET_X_REAL_TIME})" if key == "replay" else ""
            print(f"robotd replay of {seconds:.0f} s ({what}): {elapsed:.2f} s, {speed:.0f}x real time{target}")
            print(f"  taken apart ({apart}): read {stages[0]:.2f} s, replay {stages[1]:.2f} s, write {stages[2]:.2f} s")
            figures |= {
                f"{key}_seconds": elapsed,
                f"{key}_x_real_time": speed,
                f"{key}_read_s": stages[0],
                f"{key}_filters_s": stages[1],
                f"{key}_write_s": stages[2],
            }
    return figures
