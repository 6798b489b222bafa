"""Helpers for the live view's tests: a daemon in this process whose wheels roll, and fixes handed to it."""

from __future__ import annotations

from inprocess_daemon import FakeEncoders

from drivers.marvelmind.events import Position
from drivers.wheels.encoders import WheelTicks
from robotd.daemon.service import Daemon


class RollingEncoders(FakeEncoders):
    """Fake encoders whose counts grow by `counts` each publication, every wheel forward at 2 rad/s."""

    counts = 40
    total = 0

    def ticks(self, degraded: bool = False) -> WheelTicks:
        """One publication: the counts so far."""
        self.total += self.counts
        n = self.total
        return WheelTicks(self.clock(), (n, n, n, n), (2.0, 2.0, 2.0, 2.0), degraded)


def fix(daemon: Daemon, x: float, y: float) -> None:
    """A hedgehog position arriving now (measured 50 ms ago), as the Marvelmind reader hands it to the daemon."""
    now = daemon.clock()
    daemon._on_marvelmind(Position(now, now - 0.05, x, y, 0.0, 7, 1, 0.0, 0, 0, 0.05, 0x11))
