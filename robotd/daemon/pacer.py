"""When the control loop wakes: every period while the robot is commanded or moving, and hardly at all at rest.

Theory of operation. While a command is fresh (within `teleop.deadman_timeout_s`) or the controller drives, the loop
steps every control period on the loop's shared grid of wake-ups (drivers.pacing), so the encoders' publication at
the same rate falls in the same wake-up. At rest (the controller idle, in deadman or holding a fault, and no command
for the deadman timeout) the duties are zero and nothing changes without a command, which wakes the loop at once
(`command_arrived`); until one comes, it wakes only to keep pigpiod's deadman heartbeat going, `REST_BUMPS_PER_TIMEOUT`
times per deadman timeout, so a late wake-up cannot trip the deadman of a robot that is merely parked.
"""

from __future__ import annotations

import asyncio
import contextlib

from drivers.pacing import next_tick, sleep_until

REST_BUMPS_PER_TIMEOUT = 4


class ControlPacer:
    """Sleeps the control loop until its next step: the next period, or at rest the next command or heartbeat."""

    def __init__(self, period_s: float, deadman_timeout_s: float) -> None:
        self.period_s = period_s
        self.rest_period_s = max(period_s, deadman_timeout_s / REST_BUMPS_PER_TIMEOUT)
        self._command = asyncio.Event()
        self._deadline: float | None = None
        self.rest_wakeups = 0  # wake-ups at rest (heartbeats and commands), for the status and the tests

    def command_arrived(self) -> None:
        """A valid command arrived: a loop at rest steps at once and resumes its period."""
        self._command.set()

    async def next_step(self, *, at_rest: bool) -> None:
        """Wait for the next step (call it right after a step, with no await between, so no command slips by)."""
        loop = asyncio.get_running_loop()
        if at_rest:
            self._command.clear()
            # asyncio.timeout, not wait_for: Python 3.11's wait_for drops a cancellation that arrives as the event is
            # set (a command at shutdown), and the daemon's TaskGroup would then wait for this loop forever
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(self.rest_period_s):
                    await self._command.wait()
            self.rest_wakeups += 1
            self._deadline = None  # back on the grid from the next period
            return
        if self._deadline is None or self._deadline <= loop.time():  # starting, or stalled: no burst to catch up
            self._deadline = next_tick(loop.time(), self.period_s)
        await sleep_until(self._deadline)
        self._deadline += self.period_s
