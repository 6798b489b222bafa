"""The gpiod back-end's deadman: the motors' watchdog process (drivers.gpiod.watchdog) driven as the daemon drives
the deadman script in pigpiod (drivers.pigpiod.deadman.Deadman), so one keeper serves both back-ends.

`bump()` writes one heartbeat byte on the watchdog's pipe and returns (a full pipe or a gone watchdog skips it);
`watch()` reads the watchdog's reports on the event loop, calls `on_trip(trips)` for each trip and raises
DeadmanLostError when the watchdog has exited; `uninstall()` disarms it (a clean exit: the motors' close then ends
the watchdog); `close()` only stops bumping and watching, so an armed watchdog trips, as pigpio's script does when
its owner's connection is gone. The watchdog belongs to the motors (drivers.gpiod.motors.GpiodMotors), which start
it and end it.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable

from drivers.gpiod.watchdog import PwmWatchdog
from drivers.pigpiod.deadman import DeadmanLostError


class GpiodDeadman:
    """A heartbeat deadman on a running PWM watchdog; a `Deadman` (drivers.pigpiod.deadman)."""

    def __init__(self, watchdog: PwmWatchdog) -> None:
        self._watchdog = watchdog
        self._closed = False
        self._waiter: asyncio.Future[None] | None = None
        self.trips = 0

    def bump(self) -> None:
        """A heartbeat for the watchdog (never blocks)."""
        if not self._closed:
            self._watchdog.heartbeat()

    async def watch(self, on_trip: Callable[[int], None]) -> None:
        """Follow the watchdog's reports; `on_trip(trips)` after it stopped the motors; raise when it is lost."""
        loop = asyncio.get_running_loop()
        fd = self._watchdog.reports_fd
        while True:
            if self._closed:
                raise ConnectionAbortedError("the deadman was closed")
            self._waiter = loop.create_future()
            loop.add_reader(fd, _wake, self._waiter)
            try:
                await self._waiter
            finally:
                loop.remove_reader(fd)
                self._waiter = None
            trips = self._watchdog.read_reports()
            if trips is None:
                status = self._watchdog.exit_status()
                raise DeadmanLostError(f"the PWM watchdog process exited (status {status})")
            for count in trips:
                self.trips = count
                on_trip(count)

    async def uninstall(self) -> None:
        """Disarm the watchdog (it guards the owner's death only from now on) and stop following it."""
        if not self._closed:
            self._watchdog.disarm()
        self.close()

    def close(self) -> None:
        """Stop bumping and watching; an armed watchdog then trips."""
        self._closed = True
        if self._waiter is not None and not self._waiter.done():
            self._waiter.set_exception(ConnectionAbortedError("the deadman was closed"))


def _wake(waiter: asyncio.Future[None]) -> None:
    if not waiter.done():
        waiter.set_result(None)
