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

from drivers.pacing import next_tick, sleep_until

REST_BUMPS_PER_TIMEOUT = 4


def rest_period_s(period_s: float, deadman_timeout_s: float) -> float:
    """How often the loop at rest wakes, and the pace of the deadman's heartbeat either way: a few per timeout."""
    return max(period_s, deadman_timeout_s / REST_BUMPS_PER_TIMEOUT)


class ControlPacer:
    """Sleeps the control loop until its next step: the next period, or at rest the next command or heartbeat."""

    def __init__(self, period_s: float, deadman_timeout_s: float) -> None:
        self.period_s = period_s
        self.rest_period_s = rest_period_s(period_s, deadman_timeout_s)
        self._resting: asyncio.Future[None] | None = None  # what a loop at rest waits for: a command or the heartbeat
        self._deadline: float | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self.rest_wakeups = 0  # wake-ups at rest (heartbeats and commands), for the status and the tests

    def command_arrived(self) -> None:
        """A valid command arrived: a loop at rest steps at once and resumes its period."""
        _wake(self._resting)

    async def next_step(self, *, at_rest: bool) -> None:
        """Wait for the next step (call it right after a step, with no await between, so no command slips by)."""
        loop = self._loop
        if loop is None:  # asked once: Python 3.11 finds the running loop with a system call (getpid)
            loop = self._loop = asyncio.get_running_loop()
        if at_rest:
            # one future that the heartbeat's timer or a command completes: no timeout that cancels the task at
            # every heartbeat (a parked robot's main cost is its wake-ups), and a cancellation (the shutdown) reaches
            # this await like any other, even as a command arrives
            self._resting = resting = loop.create_future()
            heartbeat = loop.call_later(self.rest_period_s, _wake, resting)
            try:
                await resting
            finally:
                heartbeat.cancel()
                self._resting = None
            self.rest_wakeups += 1
            self._deadline = None  # back on the grid from the next period
            return
        if self._deadline is None or self._deadline <= loop.time():  # starting, or stalled: no burst to catch up
            self._deadline = next_tick(loop.time(), self.period_s)
        await sleep_until(self._deadline, loop)
        self._deadline += self.period_s


def _wake(resting: asyncio.Future[None] | None) -> None:
    if resting is not None and not resting.done():
        resting.set_result(None)
