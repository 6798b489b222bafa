"""The daemon's side of the deadman in pigpiod (drivers.pigpiod.deadman; on the gpiod back-end the motors' watchdog
process, drivers.gpiod.deadman): one at a time, installed with the motors, bumped by the control loop, followed for
trips and loss, removed on a clean exit.

A keeper without a factory (motors injected by a test, or `motors.deadman_script: false`) does nothing.

The control loop calls `bump` every period, but the deadman only needs a heartbeat a few times per timeout: each one
is a write to pigpiod (or the watchdog), so the keeper passes one on only when `heartbeat_s` has about passed since
the last (the loop at rest wakes every `heartbeat_s`, robotd.daemon.pacer, and bumps each time). A loop that stops
stepping still stops the heartbeats, so the motors stop within the deadman's timeout of the stall, as before.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Awaitable, Callable

from drivers.pigpiod.client import PigpioCommandError
from drivers.pigpiod.deadman import Deadman

log = logging.getLogger("robotd")

DeadmanFactory = Callable[[], Awaitable[Deadman]]

# a heartbeat is passed on once this share of `heartbeat_s` has passed: the loop at rest wakes every `heartbeat_s`,
# and its timer can fire a little before the clock read after it says the interval is over
HEARTBEAT_SLACK = 0.75


class DeadmanKeeper:
    """Holds the current deadman; says when it stopped the motors (`on_trip`) and when it was lost (`on_lost`)."""

    def __init__(
        self,
        factory: DeadmanFactory | None,
        *,
        on_trip: Callable[[int], None],
        on_lost: Callable[[OSError], None],
        uninstall_timeout_s: float,
        heartbeat_s: float = 0.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._factory = factory
        self._on_trip, self._on_lost = on_trip, on_lost
        self._uninstall_timeout_s = uninstall_timeout_s
        self._min_gap_s = HEARTBEAT_SLACK * heartbeat_s
        self._clock = clock
        self._bumped_at = -math.inf
        self.current: Deadman | None = None
        self._changed = asyncio.Event()

    async def install(self) -> None:
        """Start a deadman for the motors just connected (raises what installing it raises)."""
        if self._factory is None:
            return
        self.drop()
        self.current = await self._factory()
        self._bumped_at = -math.inf  # a new deadman hears the next bump
        self._changed.set()

    def bump(self) -> None:
        """The owner is alive (never blocks): a heartbeat for the deadman if `heartbeat_s` has about passed."""
        if self.current is None:
            return
        now = self._clock()
        if now - self._bumped_at >= self._min_gap_s:
            self._bumped_at = now
            self.current.bump()

    async def follow(self) -> None:
        """Follow each deadman in turn, forever; a lost one is dropped and reported once."""
        while True:
            await self._changed.wait()
            self._changed.clear()
            deadman = self.current
            if deadman is None:
                continue
            try:
                await deadman.watch(self._on_trip)
            except OSError as error:  # pigpiod refused, the script stopped, or the socket closed
                if deadman is self.current:  # not dropped on purpose meanwhile
                    self.drop()
                    self._on_lost(error)

    async def uninstall(self) -> None:
        """Stop and delete the current deadman (a clean exit); a failure is logged, not raised."""
        deadman, self.current = self.current, None
        if deadman is None:
            return
        try:
            async with asyncio.timeout(self._uninstall_timeout_s):  # not wait_for: 3.11's can drop a cancellation
                await deadman.uninstall()
        except (OSError, PigpioCommandError) as error:  # TimeoutError is an OSError
            log.warning("could not remove the deadman script from pigpiod (%s): it stops the motors itself", error)

    def drop(self) -> None:
        """Forget the current deadman without asking pigpiod (its connection is gone or being replaced)."""
        deadman, self.current = self.current, None
        if deadman is not None:
            deadman.close()
