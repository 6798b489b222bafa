"""Token buckets: a steady rate with a bounded burst, alone or one per source address in a bounded table.

A bucket holds at most `burst` tokens and gains `rate_per_s` of them a second; an event takes one or is refused.
`SourceRateLimiter` keeps one bucket per source in a table of at most `max_sources`: a source not in the table
starts with a full bucket and evicts the source seen least recently. A sender hopping addresses therefore costs
bounded memory and earns at most one fresh burst per hop, while a sender that keeps its address is held to its rate
and never pushes anyone else's bucket out by flooding (it stays the most recent entry, not the oldest).
All times are the caller's (monotonic seconds): no clock is read here, so tests step time by hand.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Hashable


class TokenBucket:
    """One bucket: `take()` spends a token when one is there."""

    __slots__ = ("burst", "rate_per_s", "tokens", "updated")

    def __init__(self, rate_per_s: float, burst: float, now: float) -> None:
        if rate_per_s <= 0.0 or burst < 1.0:
            raise ValueError(f"a token bucket needs a rate > 0 and a burst >= 1, got {rate_per_s}, {burst}")
        self.rate_per_s = rate_per_s
        self.burst = burst
        self.tokens = burst
        self.updated = now

    def available(self, now: float) -> float:
        """Tokens there at `now` (the bucket refilled up to then)."""
        # max(): a clock step backwards must not drain the bucket
        self.tokens = min(self.burst, self.tokens + max(now - self.updated, 0.0) * self.rate_per_s)
        self.updated = now
        return self.tokens

    def take(self, now: float) -> bool:
        """Spend one token at `now`; False (nothing spent) when the bucket is empty."""
        if self.available(now) < 1.0:
            return False
        self.tokens -= 1.0
        return True

    def spend(self, count: float) -> None:
        """Spend `count` tokens already granted by `available()`."""
        self.tokens -= count


class SourceRateLimiter:
    """A token bucket per source in a table of at most `max_sources` (the least recently seen is evicted)."""

    def __init__(self, rate_per_s: float, burst: float, max_sources: int) -> None:
        if max_sources < 1:
            raise ValueError(f"max_sources must be >= 1, got {max_sources}")
        TokenBucket(rate_per_s, burst, 0.0)  # validates the rate and burst once, here
        self.rate_per_s = rate_per_s
        self.burst = burst
        self.max_sources = max_sources
        self._buckets: OrderedDict[Hashable, TokenBucket] = OrderedDict()
        self.evicted = 0

    def admit(self, source: Hashable, now: float) -> bool:
        """One event from `source` at `now`: True when its bucket had a token."""
        buckets = self._buckets
        bucket = buckets.get(source)
        if bucket is None:
            if len(buckets) >= self.max_sources:
                buckets.popitem(last=False)
                self.evicted += 1
            bucket = buckets[source] = TokenBucket(self.rate_per_s, self.burst, now)
        else:
            buckets.move_to_end(source)
        return bucket.take(now)

    def __len__(self) -> int:
        """Sources in the table."""
        return len(self._buckets)

    def __contains__(self, source: Hashable) -> bool:
        """Whether `source` has a bucket in the table."""
        return source in self._buckets
