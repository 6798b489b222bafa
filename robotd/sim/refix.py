"""Simulated IPS fixes on a recorded log's truth: a real robot's odometry and motion-capture truth, its fixes made by
the virtual hedgehog (robotd.sim.ips), as the logs robotd is judged on are made. Pure: events in, events out.

The hedgehog measures the beacon where the truth puts it (the robot's centre, linear between truth samples, moved by
the beacon's offset turned by the truth's heading) with the configuration's rate, latency, noise and dropouts
(`sim.ips_*`). The kinds are the judged logs': `clean` (no outliers, no outages), `untimed` (clean, but the lines carry
no measurement time: the filter must learn the delay) and `harsh` (as `robotd simulate harsh`: outlier bursts four
times as often as configured, an 8 s outage in the middle, no measurement times). Everything else in the log is kept;
its own fixes and lost-fix records are replaced.

Not modelled: what `robotd.sim.ips` does not model (the beacons' geometry, the speed of sound), and motion between
truth samples other than a straight line at constant speed.
"""

from __future__ import annotations

import bisect
import dataclasses
import math
from collections.abc import Sequence

from robotd.logs.sensorlog import Event, IpsFix, IpsLost, Truth
from robotd.sim.ips import Hedgehog, IpsParams
from robotd.sim.offline import fix_event

KINDS = ("clean", "untimed", "harsh")
HARSH_OUTAGE_S = 8.0  # the judged harsh logs' outage, centred in the log
HARSH_BURST_FACTOR = 4.0  # outlier bursts this many times as often as configured (as the `harsh` scenario)


class TruthError(ValueError):
    """The log's truth cannot place the beacon: none at all, or no heading where the beacon is off the centre."""


def params_for(kind: str, configured: IpsParams) -> IpsParams:
    """The hedgehog's error model for a kind of log, from the configured one."""
    if kind not in KINDS:
        raise ValueError(f"unknown kind {kind!r}; known: {', '.join(KINDS)}")
    if kind == "harsh":
        burst_rate = HARSH_BURST_FACTOR * configured.outlier_burst_rate_per_min
        return dataclasses.replace(configured, outlier_burst_rate_per_min=burst_rate, outage_rate_per_min=0.0)
    return dataclasses.replace(configured, outlier_burst_rate_per_min=0.0, outage_rate_per_min=0.0)


class _Beacon:
    """Where the truth puts the beacon at any time within its span."""

    def __init__(self, truth: Sequence[Truth], offset: tuple[float, float]) -> None:
        if len(truth) < 2:
            raise TruthError("the log has fewer than two truth samples: no truth to measure fixes on")
        if offset != (0.0, 0.0) and any(math.isnan(sample.theta) for sample in truth):
            raise TruthError(f"the beacon is {offset} m off the centre and the truth has no heading to place it")
        self.t = [sample.t for sample in truth]
        self.samples = truth
        self.offset = offset

    def at(self, t: float) -> tuple[float, float]:
        """The beacon's true position at t (the first or last sample's outside the span)."""
        samples = self.samples
        i = min(max(bisect.bisect_right(self.t, t), 1), len(samples) - 1)
        a, b = samples[i - 1], samples[i]
        f = min(max((t - a.t) / (b.t - a.t), 0.0), 1.0) if b.t > a.t else 1.0
        x, y = a.x + f * (b.x - a.x), a.y + f * (b.y - a.y)
        ox, oy = self.offset
        if ox or oy:
            turn = math.remainder(b.theta - a.theta, math.tau)
            theta = a.theta + f * turn
            c, s = math.cos(theta), math.sin(theta)
            x, y = x + ox * c - oy * s, y + ox * s + oy * c
        return x, y


def refixed(
    events: Sequence[Event], configured: IpsParams, kind: str, seed: int, offset: tuple[float, float]
) -> list[Event]:
    """The log's events with its fixes replaced by the hedgehog's of this kind and seed, measured on its truth (the
    beacon `offset` m from the centre, robot frame); in time order, a fix after the events of its time."""
    params = params_for(kind, configured)
    truth = [event for event in events if type(event) is Truth]
    beacon = _Beacon(truth, offset)
    start, end = truth[0].t, truth[-1].t
    outages: tuple[tuple[float, float], ...] = ()
    if kind == "harsh":
        middle = 0.5 * (start + end)
        outages = ((middle - 0.5 * HARSH_OUTAGE_S, middle + 0.5 * HARSH_OUTAGE_S),)
    hedgehog = Hedgehog(params, seed, outages, start_s=start)
    while hedgehog.next_measurement_s <= end:
        now = hedgehog.next_measurement_s
        hedgehog.measure(now, *beacon.at(now))
    fixes: list[Event] = []
    for packet in hedgehog.due(math.inf):
        fix = fix_event(packet, packet.arrival_s)
        if kind != "clean" and type(fix) is IpsFix:
            fix = IpsFix(fix.t, fix.x, fix.y, fix.z)  # the line carries no measurement time
        fixes.append(fix)
    kept = [event for event in events if type(event) is not IpsFix and type(event) is not IpsLost]
    merged = sorted([(e.t, 0, e) for e in kept] + [(e.t, 1, e) for e in fixes], key=lambda item: (item[0], item[1]))
    return [event for _, _, event in merged]


__all__ = ["HARSH_BURST_FACTOR", "HARSH_OUTAGE_S", "KINDS", "TruthError", "params_for", "refixed"]
