"""Capped exponential delays between reconnection attempts: the one backoff of every link that reconnects."""

from __future__ import annotations


class Backoff:
    """Capped exponential delays between reconnection attempts."""

    def __init__(self, first_s: float, cap_s: float) -> None:
        self.first_s = min(first_s, cap_s)
        self.cap_s = cap_s
        self._next_s = self.first_s

    def next_delay(self) -> float:
        """The wait before the next attempt; each call doubles the following one, up to the cap."""
        delay = self._next_s
        self._next_s = min(self._next_s * 2.0, self.cap_s)
        return delay

    def reset(self) -> None:
        """After a success: start again from the first delay."""
        self._next_s = self.first_s
