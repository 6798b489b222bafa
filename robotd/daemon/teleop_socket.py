"""The teleop socket on the event loop: datagrams read in bounded batches, answers sent back, commands handed on.

Theory of operation. asyncio's datagram transport reads one datagram per loop iteration, and nothing bounds how
many iterations a flood takes. Here a reader callback reads the non-blocking socket directly: at most `BATCH`
datagrams per wake-up, so timers (the control loop) run between batches, and at most `read_budget_per_s` a second
over all sources: once the budget is spent, reading pauses until it refills and the kernel drops the excess, so a
flood costs the daemon a bounded share of the CPU and the control loop is not starved of it. Each datagram read
goes to the receiver with its source address, whose rate limit is the first check. A flood is reported in the log,
at most once every `FLOOD_REPORT_S`.

Two ways to be read: on arrival (`watch(True)`, the selector wakes the loop for each datagram) or when the owner polls
(`watch(False)` and `poll()`). The daemon's control loop polls at every period while the wheels are driven, so the
commands of a 20 Hz teleop client cost no wake-ups of their own, and watches while they are not, so a command that
starts them reaches the motors at once.
"""

from __future__ import annotations

import asyncio
import logging
import socket
import time
from collections.abc import Callable

from robotd.config.model import TeleopConfig
from robotd.daemon.ratelimit import TokenBucket
from robotd.daemon.teleop import DATAGRAM_SIZE, Answer, Reject, TeleopMessage, TeleopReceiver

log = logging.getLogger(__name__)

BATCH = 32  # datagrams read per wake-up at most: about 50 us of work between two looks at the timers
BUDGET_S = 0.05  # the read budget holds this many seconds of reads: a burst of real traffic passes whole
FLOOD_REPORT_S = 10.0


class TeleopSocket:
    """Reads teleop datagrams off the loop's selector in bounded batches (see the module docstring)."""

    def __init__(
        self,
        sock: socket.socket,
        receiver: TeleopReceiver,
        on_message: Callable[[TeleopMessage], None],
        *,
        read_budget_per_s: float,
        clock: Callable[[], float] = time.monotonic,
        wall_clock: Callable[[], float] = time.time,
    ) -> None:
        self.sock = sock
        self.receiver = receiver
        self.on_message = on_message
        self.clock = clock
        self.wall_clock = wall_clock
        self._budget = TokenBucket(read_budget_per_s, max(float(BATCH), read_budget_per_s * BUDGET_S), clock())
        self._loop = asyncio.get_running_loop()
        self._resume: asyncio.TimerHandle | None = None
        self._reported_at = clock()
        self._reported = (0, 0)  # rate_limited and read_pauses at the last report
        self._watching = True
        sock.setblocking(False)
        self._loop.add_reader(sock.fileno(), self._readable)

    @property
    def watching(self) -> bool:
        """Whether datagrams are read on arrival (else only by `poll`)."""
        return self._watching

    def watch(self, watching: bool) -> None:
        """Read each datagram on arrival (True), or only when `poll` is called (False)."""
        if watching == self._watching:
            return
        self._watching = watching
        if self._resume is not None:  # reading is paused: the resumption follows the new choice
            return
        if watching:
            self._loop.add_reader(self.sock.fileno(), self._readable)
        else:
            self._loop.remove_reader(self.sock.fileno())

    def poll(self) -> None:
        """Read what has arrived, as on arrival (nothing while a spent read budget pauses reading)."""
        if self._resume is None:
            self._readable()

    def _readable(self) -> None:
        try:
            datagram = self._receive()
        except (BlockingIOError, InterruptedError):
            return  # nothing arrived (most of the driving loop's polls): no clock or budget to consult
        clock = self.clock
        now = clock()
        # the first datagram is read before the budget is asked: reading pauses while the budget is spent, so it
        # holds at least that one whenever this runs
        allowed = max(1, min(BATCH, int(self._budget.available(now))))
        wall_time = self.wall_clock()
        read = 0
        while True:
            read += 1
            if datagram is not None:
                data, address = datagram
                outcome = self.receiver.datagram(data, clock(), wall_time, address[0])
                if isinstance(outcome, Answer):
                    self._answer(outcome, address)
                elif outcome is not None:
                    self.on_message(outcome)
            if read >= allowed:
                break
            try:
                datagram = self._receive()
            except (BlockingIOError, InterruptedError):
                break
        self._budget.spend(read)
        if read == allowed < BATCH:  # the budget, not the queue, ended the batch: pause until it refills
            self._pause()
        if now - self._reported_at >= FLOOD_REPORT_S:
            self._report(now)

    def _receive(self) -> tuple[bytes, tuple[str | int, ...]] | None:
        """The next datagram and its source address; None for an error queued on the socket (an ICMP error: normal
        on UDP, keep serving); BlockingIOError when nothing is queued."""
        try:
            return self.sock.recvfrom(DATAGRAM_SIZE + 1)  # one byte more tells an oversized datagram
        except (BlockingIOError, InterruptedError):
            raise
        except OSError as error:
            log.debug("teleop socket error: %s", error)
            return None

    def _answer(self, answer: Answer, address: tuple[str | int, ...]) -> None:
        try:
            self.sock.sendto(answer.datagram, address)
        except OSError as error:  # a full send buffer or an unreachable client: the client asks again
            log.debug("teleop answer to %s not sent: %s", address[0], error)

    def _pause(self) -> None:
        self.receiver.read_pauses += 1
        if self._watching:
            self._loop.remove_reader(self.sock.fileno())
        self._resume = self._loop.call_later(BATCH / self._budget.rate_per_s, self._resume_reading)

    def _resume_reading(self) -> None:
        self._resume = None
        if self._watching:
            self._loop.add_reader(self.sock.fileno(), self._readable)

    def _report(self, now: float) -> None:
        """Say in the log what a flood cost since the last report (called at most once every FLOOD_REPORT_S)."""
        limited, pauses = self.receiver.rejected[Reject.RATE_LIMITED], self.receiver.read_pauses
        if (limited, pauses) != self._reported:
            log.warning(
                "teleop flood: %d datagrams over the per-source rate and %d read pauses in the last %.0f s",
                limited - self._reported[0],
                pauses - self._reported[1],
                now - self._reported_at,
            )
        self._reported_at, self._reported = now, (limited, pauses)

    def close(self) -> None:
        """Stop reading and close the socket."""
        if self._resume is not None:
            self._resume.cancel()
            self._resume = None
        self._loop.remove_reader(self.sock.fileno())
        self.sock.close()


async def open_teleop(
    config: TeleopConfig, receiver: TeleopReceiver, on_message: Callable[[TeleopMessage], None]
) -> TeleopSocket:
    """Listen for teleop datagrams on the configured address; the caller closes the socket."""
    loop = asyncio.get_running_loop()
    infos = await loop.getaddrinfo(config.bind, config.port, type=socket.SOCK_DGRAM)
    family, kind, proto, _name, address = infos[0]
    sock = socket.socket(family, kind, proto)
    try:
        sock.bind(address)
        return TeleopSocket(sock, receiver, on_message, read_budget_per_s=config.read_budget_per_s)
    except BaseException:
        sock.close()
        raise
