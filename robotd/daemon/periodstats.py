"""A loop's period over the last second: the control loop's health, reported in the daemon's status."""

from __future__ import annotations

import collections
import math


class PeriodStats:
    """Intervals between a loop's scheduled ticks over the last `window_s`: p50, p99 and max, in milliseconds."""

    def __init__(self, window_s: float = 1.0) -> None:
        self.window_s = window_s
        self._ticks: collections.deque[tuple[float, float]] = collections.deque()  # (tick time, interval)
        self._previous: float | None = None

    def tick(self, now: float) -> None:
        """Note a scheduled tick at `now`."""
        if self._previous is not None:
            self._ticks.append((now, now - self._previous))
        self._previous = now
        while self._ticks and self._ticks[0][0] < now - self.window_s:
            self._ticks.popleft()

    def pause(self) -> None:
        """The loop stops ticking for a while: the interval until its next tick is not a period."""
        self._previous = None

    def summary(self) -> dict[str, float | int]:
        """{"p50_ms", "p99_ms", "max_ms", "ticks"} over the window (NaN without a tick; encoded as null)."""
        intervals = sorted(interval for _, interval in self._ticks)
        if not intervals:
            return {"p50_ms": math.nan, "p99_ms": math.nan, "max_ms": math.nan, "ticks": 0}
        last = len(intervals) - 1
        return {
            "p50_ms": 1e3 * intervals[round(0.50 * last)],
            "p99_ms": 1e3 * intervals[round(0.99 * last)],
            "max_ms": 1e3 * intervals[last],
            "ticks": len(intervals),
        }
