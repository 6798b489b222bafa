"""The Marvelmind hedgehog's error model: true beacon positions in, position packets with their arrival times out.

Theory of operation: the hedgehog measures at a jittered rate. Each measurement is the beacon's true position plus
Gaussian noise, unless it falls in an outage (the packet says "coordinates unavailable"), is a random dropout (the
same), or falls in an outlier burst (the fix is thrown 1-4.6 m away in the burst's direction, as echoes do). Each
packet then takes a random latency to reach the host; the serial line is first in, first out, so a packet never
overtakes its predecessor. The packet carries what a real one carries: the beacon's millisecond timestamp, the
position quantised to the frame's unit (mm for code 0x0011, cm for 0x0001) and the time-shift field, the time from
measurement to sending in ms. Outages and bursts are Poisson episodes; an experiment can force outages at given times.

Not modelled: the beacons' geometry (noise is the same everywhere), the speed of sound, the IMU, packets of other
hedgehogs, the modem's buffering.
"""

from __future__ import annotations

import math
import random
from collections import deque
from dataclasses import dataclass

from drivers.virtual.marvelmind import POSITION_CM, POSITION_MM, HedgehogPacket


@dataclass(frozen=True, slots=True)
class IpsParams:
    """The hedgehog's rate, latency and errors."""

    rate_hz: float = 12.0
    interval_jitter: float = 0.1
    latency_s: tuple[float, float] = (0.05, 0.15)
    noise_m: float = 0.03
    noise_z_m: float = 0.05
    height_m: float = 0.3
    dropout_probability: float = 0.03
    outage_rate_per_min: float = 0.5
    outage_duration_s: tuple[float, float] = (1.0, 5.0)
    outlier_burst_rate_per_min: float = 0.6
    outlier_burst_duration_s: tuple[float, float] = (0.5, 2.5)
    outlier_m: tuple[float, float] = (1.0, 4.6)
    frame_code: int = POSITION_MM
    address: int = 7


class _Episodes:
    """A Poisson process of episodes (start, end), queried at increasing times."""

    def __init__(self, rng: random.Random, rate_per_min: float, duration_s: tuple[float, float]) -> None:
        self._rng = rng
        self._rate_hz = rate_per_min / 60.0
        self._duration = duration_s
        self.start, self.end = self._draw(0.0)

    def _draw(self, after: float) -> tuple[float, float]:
        if self._rate_hz <= 0.0:
            return math.inf, math.inf
        start = after + self._rng.expovariate(self._rate_hz)
        return start, start + self._rng.uniform(*self._duration)

    def active(self, t: float) -> bool:
        """Whether an episode covers time t (t never decreases between calls)."""
        while t >= self.end:
            self.start, self.end = self._draw(self.end)
        return self.start <= t


class Hedgehog:
    """The hedgehog: `measure()` when `next_measurement_s` is reached, `due(now)` for packets that have arrived."""

    def __init__(
        self, params: IpsParams, seed: int, forced_outages: tuple[tuple[float, float], ...] = (), start_s: float = 0.0
    ) -> None:
        self.params = params
        self._rng = random.Random(f"robotd-sim:{seed}:ips")
        self._outages = _Episodes(
            random.Random(f"robotd-sim:{seed}:outages"), params.outage_rate_per_min, params.outage_duration_s
        )
        self._bursts = _Episodes(
            random.Random(f"robotd-sim:{seed}:bursts"),
            params.outlier_burst_rate_per_min,
            params.outlier_burst_duration_s,
        )
        self._burst_direction = 0.0
        self._burst_start = -math.inf
        self._forced = forced_outages
        self._wake_ms = self._rng.randrange(0, 2**32)  # the beacon woke up long before the run
        self._last_arrival = -math.inf
        self._in_flight: deque[HedgehogPacket] = deque()
        self.next_measurement_s = start_s + self._interval()

    def _interval(self) -> float:
        nominal = 1.0 / self.params.rate_hz
        return max(0.2 * nominal, nominal * (1.0 + self._rng.gauss(0.0, self.params.interval_jitter)))

    def _lost(self, t: float) -> bool:
        forced = any(start <= t < end for start, end in self._forced)
        return self._outages.active(t) or forced or self._rng.random() < self.params.dropout_probability

    def measure(self, t: float, beacon_x: float, beacon_y: float) -> None:
        """Measure the beacon's true position (m, world frame) at time t; schedules the packet and the next one."""
        p = self.params
        rng = self._rng
        x = beacon_x + rng.gauss(0.0, p.noise_m)
        y = beacon_y + rng.gauss(0.0, p.noise_m)
        z = p.height_m + rng.gauss(0.0, p.noise_z_m)
        available = not self._lost(t)
        if self._bursts.active(t):
            if self._bursts.start != self._burst_start:  # a new burst: the echo comes from a new direction
                self._burst_start = self._bursts.start
                self._burst_direction = rng.uniform(0.0, 2.0 * math.pi)
            distance = rng.uniform(*p.outlier_m)
            direction = self._burst_direction + rng.gauss(0.0, 0.3)
            x += distance * math.cos(direction)
            y += distance * math.sin(direction)
        arrival = max(t + rng.uniform(*p.latency_s), self._last_arrival + 0.001)  # FIFO: no overtaking
        self._last_arrival = arrival
        shift_ms = min(0xFFFF, round((arrival - t) * 1000.0))
        self._in_flight.append(
            HedgehogPacket(
                arrival_s=arrival,
                measured_s=t,
                timestamp_ms=(self._wake_ms + round(t * 1000.0)) & 0xFFFFFFFF,
                x_mm=_quantised_mm(x, p.frame_code),
                y_mm=_quantised_mm(y, p.frame_code),
                z_mm=_quantised_mm(z, p.frame_code),
                available=available,
                time_shift_ms=shift_ms,
                address=p.address,
                frame_code=p.frame_code,
            )
        )
        self.next_measurement_s = t + self._interval()

    @property
    def next_arrival_s(self) -> float:
        """When the oldest packet in flight arrives (inf when none is)."""
        return self._in_flight[0].arrival_s if self._in_flight else math.inf

    def due(self, now: float) -> list[HedgehogPacket]:
        """Packets that have arrived by `now`, in arrival order."""
        arrived = []
        while self._in_flight and self._in_flight[0].arrival_s <= now:
            arrived.append(self._in_flight.popleft())
        return arrived


def _quantised_mm(value_m: float, frame_code: int) -> int:
    """A coordinate as the frame carries it, in mm (a multiple of 10 for the cm frame)."""
    if frame_code == POSITION_CM:
        return 10 * max(-32768, min(32767, round(value_m * 100.0)))
    return max(-(2**31), min(2**31 - 1, round(value_m * 1000.0)))
