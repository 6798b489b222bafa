"""Synthetic sensor logs with known truth: the paper's square drive with slip, and Marvelmind-like fixes.

A pure generator (seeded, no I/O): the true robot follows velocity commands, but the floor turns it slowly (heading
drift while moving, from unequal traction) and its wheels slip a little, so the encoders (which see the commanded
wheel turns) disagree with the truth as the paper's odometry did. Fixes come at a Marvelmind-like rate with latency,
Gaussian noise, bursts of multi-metre outliers and outages ("coordinates unavailable").
It is a test fixture, not the virtual robot (drivers/sim/ models motors and the real protocols).
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass

from robotd import kinematics
from robotd.logfile import Event, IpsFix, IpsLost, Meta, Truth, Wheels


@dataclass(frozen=True, slots=True)
class SynthSpec:
    """What to generate; defaults are a realistic Marvelmind on the paper's robot."""

    loops: int = 2
    side_m: float = 3.0
    speed_mps: float = 0.3
    wheel_rate_hz: float = 100.0
    fix_rate_hz: float = 8.0
    latency_s: tuple[float, float] = (0.03, 0.15)
    noise_m: float = 0.03
    drift_rad_per_m: float = 0.04  # the floor turns the robot while it moves
    slip_frac: float = 0.03  # true speed differs from the wheels' by this fraction
    outlier_bursts_per_min: float = 2.0
    outlier_m: tuple[float, float] = (1.0, 3.0)
    outlier_burst_fixes: tuple[int, int] = (1, 3)
    outages: int = 1
    outage_s: float = 4.0
    ips_offset_m: tuple[float, float] = (0.0, 0.0)
    pause_s: float = 1.0


def _segments(spec: SynthSpec) -> list[tuple[float, float, float, float]]:
    """(duration, vx, vy, wz) commands: pause, then the square +x, -y, -x, +y, per loop."""
    t_side = spec.side_m / spec.speed_mps
    v = spec.speed_mps
    legs = [(t_side, v, 0.0, 0.0), (t_side, 0.0, -v, 0.0), (t_side, -v, 0.0, 0.0), (t_side, 0.0, v, 0.0)]
    out = [(spec.pause_s, 0.0, 0.0, 0.0)]
    for _ in range(spec.loops):
        for leg in legs:
            out += [leg, (0.5, 0.0, 0.0, 0.0)]
    return out


def generate(spec: SynthSpec, seed: int) -> tuple[Meta, list[Event]]:
    """A log (meta and events in arrival order) of the square drive with known truth."""
    rng = random.Random(seed)
    geometry = kinematics.Geometry()
    cpr = 6800
    dt = 1.0 / spec.wheel_rate_hz
    x = y = th = 0.0
    wheel_angle = [0.0, 0.0, 0.0, 0.0]
    drift_sign = rng.choice((-1.0, 1.0))
    events: list[tuple[float, int, Event]] = []
    truth: list[tuple[float, float, float, float]] = []
    t = 0.0
    order = 0
    for duration, vx_c, vy_c, wz_c in _segments(spec):
        for _ in range(round(duration / dt)):
            # the wheels turn as commanded (speed control); the body slips and the floor turns it
            speeds = kinematics.inverse(geometry, kinematics.Twist(vx_c, vy_c, wz_c))
            for i in range(4):
                wheel_angle[i] += speeds[i] * dt
            moving = math.hypot(vx_c, vy_c)
            scale = 1.0 + spec.slip_frac * (0.5 + 0.5 * math.sin(t / 7.0))
            wz_true = wz_c + drift_sign * spec.drift_rad_per_m * moving * (1.0 + 0.5 * math.sin(t / 5.0))
            mid = th + 0.5 * wz_true * dt
            c, s = math.cos(mid), math.sin(mid)
            x += (vx_c * scale * c - vy_c * scale * s) * dt
            y += (vx_c * scale * s + vy_c * scale * c) * dt
            th += wz_true * dt
            t += dt
            ticks = tuple(math.floor(a * cpr / (2.0 * math.pi)) for a in wheel_angle)
            events.append((t, order, Wheels(t, (ticks[0], ticks[1], ticks[2], ticks[3]))))
            order += 1
            truth.append((t, x, y, th))
    for tt, tx, ty, tth in truth[::2]:
        events.append((tt, order, Truth(tt, tx, ty, tth)))
        order += 1
    end = truth[-1][0]
    outages = [(rng.uniform(0.2 * end, 0.9 * end), spec.outage_s) for _ in range(spec.outages)]
    burst_left = 0
    burst_offset = (0.0, 0.0)
    last_arrival = 0.0
    t_meas = 1.0 / spec.fix_rate_hz
    ox, oy = spec.ips_offset_m
    while t_meas < end - 0.2:
        latency = rng.uniform(*spec.latency_s)
        arrival = max(t_meas + latency, last_arrival + 1e-4)
        last_arrival = arrival
        index = min(int(t_meas * spec.wheel_rate_hz), len(truth) - 1)
        _, tx, ty, tth = truth[index]
        if any(start <= t_meas < start + length for start, length in outages):
            events.append((arrival, order, IpsLost(arrival)))
        else:
            bx = tx + ox * math.cos(tth) - oy * math.sin(tth) + rng.gauss(0.0, spec.noise_m)
            by = ty + ox * math.sin(tth) + oy * math.cos(tth) + rng.gauss(0.0, spec.noise_m)
            if burst_left == 0 and rng.random() < spec.outlier_bursts_per_min / 60.0 / spec.fix_rate_hz:
                burst_left = rng.randint(*spec.outlier_burst_fixes)
                burst_offset = (0.0, 0.0)
            if burst_left > 0:
                burst_left -= 1
                angle = rng.uniform(-math.pi, math.pi)
                size = rng.uniform(*spec.outlier_m)
                burst_offset = (size * math.cos(angle), size * math.sin(angle))
                bx, by = bx + burst_offset[0], by + burst_offset[1]
            events.append((arrival, order, IpsFix(arrival, bx, by, 0.0, t_meas)))
        order += 1
        t_meas += 1.0 / spec.fix_rate_hz * rng.uniform(0.9, 1.1)
    events.sort(key=lambda item: (item[0], item[1]))
    meta = Meta(
        robot={
            "wheel_radius": geometry.wheel_radius_m,
            "lx": geometry.lx_m,
            "ly": geometry.ly_m,
            "counts_per_rev": cpr,
            "ips_offset": list(spec.ips_offset_m),
        },
        source=f"robotd.synthlog seed={seed} {spec}",
    )
    return meta, [event for _, _, event in events]


__all__ = ["SynthSpec", "generate"]
