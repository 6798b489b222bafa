"""Wheel encoders read from pigpiod's notification stream in batches paced to their consumers, on the event loop.

Theory of operation: `PigpioEncoders` configures the encoder pins over a command socket (input, pull, glitch
filter), opens a second socket with NOIB and starts notifications (NB) for the eight pins. pigpiod then writes a
12-byte report per level change, flushed every millisecond. The event loop does not watch that socket: the reports
wait in the kernel, and the publisher takes them all at each publication (`publish_rate_hz`, on the loop's shared
grid of wake-ups, drivers.pacing) with one non-blocking receive, and hands the batch to numpy: sequence gaps
counted, ticks unwrapped, quadrature decoded (drivers.wheels.quadrature); then `WheelTicks` go to the daemon. One
wake-up per publication, whatever the edge rate: no thread, no Python per edge. The sequence numbers make a lost
report visible however the reports are batched.

At rest: after `IDLE_AFTER_QUIET` publications in a row that brought no report, the source stops waking at the
publication rate: it watches the socket for the next edge (publishing at once when it comes, then at the rate again)
and publishes every `IDLE_KEEPALIVE_S` meanwhile, the heartbeat the daemon's health check reads.

Connection policy: the first connection failing raises `PigpiodUnavailableError` (a wrong host or a stopped pigpiod is
a configuration problem to report at once). A connection lost later (seen by the publisher's read, or by the
re-anchoring command) is retried with exponential backoff up to `pigpiod.reconnect_max_s`; meanwhile and for the first
publication after it, `degraded` is true, the counts keep their last values and the speeds read 0. Edges during the
outage are lost: the odometry says so, never guesses.

Back-end seam: the daemon depends only on `EncoderSource` (and `WheelTicks`); an lgpio back-end for the Pi 5 and
Raspberry Pi OS 13, where pigpio does not run, would be a second class with the same `run()`.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from drivers.backoff import Backoff
from drivers.pacing import next_tick, sleep_until
from drivers.pigpiod.client import PigpioCommandError, PigpiodUnavailableError, PigpioLink, open_notification_socket
from drivers.pigpiod.notifications import SequenceGaps, TickClock
from drivers.pigpiod.protocol import REPORT_SIZE, Cmd, Mode, Pull, decode_reports
from drivers.settings import EncoderSettings, PigpiodAddress, in_wheel_order
from drivers.wheels.quadrature import EdgeTimedSpeed, EncoderWiring, QuadratureDecoder

log = logging.getLogger("robotd.encoders")

READ_CHUNK_BYTES = 1 << 16
"""One receive takes up to this much (5461 reports); a fuller kernel buffer takes another."""
RESYNC_PERIOD_S = 5.0
"""How often the tick-to-monotonic map is re-anchored (follows drift between pigpio's and the kernel's clocks)."""
FIRST_RETRY_S = 0.05
IDLE_AFTER_QUIET = 10
"""Publications in a row without a report before the source waits for an edge instead of the clock."""
IDLE_KEEPALIVE_S = 0.5
"""An idle source still publishes this often: publications are the filter's heartbeat for the daemon's health check."""


@dataclass(frozen=True, slots=True)
class WheelTicks:
    """Cumulative encoder counts per wheel (FL, FR, RL, RR) at monotonic time `t`, and wheel speeds."""

    t: float
    ticks: tuple[int, int, int, int]
    speeds_rad_s: tuple[float, float, float, float]
    degraded: bool
    """True when reports were lost, a transition was illegal or pigpiod was unreachable since the last one."""


@dataclass(frozen=True, slots=True)
class EncoderCounters:
    """Health of the encoder stream since start."""

    reports: int
    lost_reports: int
    illegal_transitions: tuple[int, int, int, int]
    reconnects: int


class EncoderSource(Protocol):
    """What the daemon needs from an encoder back-end."""

    @property
    def counters(self) -> EncoderCounters:
        """Health counters."""
        ...

    async def run(self, on_ticks: Callable[[WheelTicks], None]) -> None:
        """Publish wheel ticks until cancelled."""
        ...


def wiring(encoders: EncoderSettings) -> list[EncoderWiring]:
    """The encoders' pins and signs in wheel order."""
    return [EncoderWiring(pins.a, pins.b, pins.sign) for pins in in_wheel_order(encoders.wheels)]


def pin_mask(encoders: EncoderSettings) -> int:
    """The bank-1 bits of every encoder pin."""
    return sum((1 << w.a) | (1 << w.b) for w in wiring(encoders))


_PULLS = {"up": Pull.UP, "down": Pull.DOWN, "off": Pull.OFF}


class PigpioEncoders:
    """Encoder source on pigpiod's notification socket (see the module docstring)."""

    def __init__(
        self, encoders: EncoderSettings, pigpiod: PigpiodAddress, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self._encoders = encoders
        self._pigpiod = pigpiod
        self._clock = clock
        self._wiring = wiring(encoders)
        self._mask = pin_mask(encoders)
        self._radians_per_count = 2 * math.pi / encoders.counts_per_rev
        self._decoder = QuadratureDecoder(self._wiring, encoders.decoding, 0)
        self._speed = EdgeTimedSpeed(len(self._wiring), stale_after_us=self._stale_after_us())
        self._gaps = SequenceGaps()
        self._tick_clock: TickClock | None = None
        self._unread = bytearray()
        self._stream: socket.socket | None = None  # the notification socket while it is up (polled, never watched)
        self._lost = asyncio.Event()  # the publisher found the stream broken
        self._lost_error: BaseException | None = None
        self._edge: asyncio.Future[None] | None = None  # an idle publisher waiting for the next edge
        self.wakeups = 0  # publications, for the tests' count of the source's own wake-ups
        self._connected = False
        self._degraded = False
        self._reports = 0
        self._reconnects = 0

    def _stale_after_us(self) -> int:
        return round(2e6 / self._encoders.publish_rate_hz)

    @property
    def counters(self) -> EncoderCounters:
        """Health counters since start."""
        illegal = tuple(int(n) for n in self._decoder.illegal)
        return EncoderCounters(self._reports, self._gaps.lost, (illegal[0], illegal[1], illegal[2], illegal[3]),
                               self._reconnects)  # fmt: skip

    @property
    def connected(self) -> bool:
        """True while the notification stream is up."""
        return self._connected

    @property
    def ticks(self) -> tuple[int, ...]:
        """The cumulative counts decoded so far, in wheel order."""
        return tuple(int(n) for n in self._decoder.counts)

    async def run(self, on_ticks: Callable[[WheelTicks], None]) -> None:
        """Connect (or raise PigpiodUnavailableError), then publish wheel ticks until cancelled."""
        link = await self._connect()
        async with asyncio.TaskGroup() as tasks:
            tasks.create_task(self._publish(on_ticks), name="encoders-publish")
            tasks.create_task(self._stay_connected(link), name="encoders-stream")

    async def _connect(self) -> PigpioLink:
        """Configure the pins and start notifications on a polled socket; returns the command link."""
        host, port, timeout = self._pigpiod.host, self._pigpiod.port, self._pigpiod.connect_timeout_s
        link = await PigpioLink.connect(host, port, timeout)
        stream: socket.socket | None = None
        try:
            for encoder in self._wiring:
                for gpio in (encoder.a, encoder.b):
                    await link.command(Cmd.MODES, gpio, Mode.INPUT)
                    await link.command(Cmd.PUD, gpio, _PULLS[self._encoders.pull])
                    await link.command(Cmd.FG, gpio, self._encoders.glitch_filter_us)
            handle, stream = await open_notification_socket(host, port, timeout)
            levels = await link.command(Cmd.BR1, unsigned=True)
            before = self._clock()
            tick = await link.command(Cmd.TICK, unsigned=True)
            self.begin_stream(levels, tick, (before + self._clock()) / 2, streaming=False)
            await link.command(Cmd.NB, handle, self._mask)
            # connected once pigpiod reports: a caller that drove edges as soon as `connected` said so, before NB
            # reached pigpiod (a busy machine), saw none of them reported
            self._connected = True
        except BaseException:
            self._connected = False
            if stream is not None:
                stream.close()
            await link.close()
            raise
        self._stream = stream
        self._lost.clear()
        return link

    def begin_stream(self, levels: int, tick: int, monotonic_s: float, *, streaming: bool = True) -> None:
        """Start decoding a new stream from bank-1 `levels`, with `tick` read at `monotonic_s`; `connected` from now
        when `streaming` (reports already flow), else once the caller has started them.

        Its sequence restarts and its edge times start a new time line; counts carry on.
        """
        self._unread.clear()
        self._decoder.restart(levels)
        self._gaps.restart()
        self._tick_clock = TickClock(tick, monotonic_s)
        self._speed = EdgeTimedSpeed(len(self._wiring), stale_after_us=self._stale_after_us())
        self._connected = streaming

    async def _stay_connected(self, link: PigpioLink) -> None:
        """Re-anchor the tick map while the stream is up; when it breaks, reconnect with backoff."""
        backoff = Backoff(FIRST_RETRY_S, self._pigpiod.reconnect_max_s)
        while True:
            # two tasks waited on by hand, not a TaskGroup: a cancellation arriving as the stream breaks (the daemon
            # stopping while pigpiod goes too) must end this task, and 3.11's TaskGroup can drop it for the child's
            # error, after which the task reconnected forever
            watchers = (asyncio.ensure_future(self._until_lost()), asyncio.ensure_future(self._resync(link)))
            try:
                done, _ = await asyncio.wait(watchers, return_when=asyncio.FIRST_COMPLETED)
                for watcher in done:
                    watcher.result()  # the error that broke the stream (a return would be a bug: neither returns)
            except (OSError, EOFError) as error:
                log.warning("encoder stream from pigpiod lost (%s): odometry degraded, reconnecting", error)
            finally:
                for watcher in watchers:
                    watcher.cancel()
                await asyncio.wait(watchers)
                self._read_available()  # what arrived before the break still counts
                self._close_stream()
                self._degraded = True
                await link.close()
            while True:
                await asyncio.sleep(backoff.next_delay())
                try:
                    # bounded as a whole: a pigpiod that accepts but stalls must not hold the encoders forever
                    async with asyncio.timeout(4 * self._pigpiod.connect_timeout_s):
                        link = await self._connect()
                except (PigpiodUnavailableError, OSError, PigpioCommandError) as error:
                    log.debug("encoders: pigpiod still unavailable: %s", error)
                    continue
                self._reconnects += 1
                backoff.reset()
                log.info("encoder stream from pigpiod restored")
                break

    async def _until_lost(self) -> None:
        """Return never; raise what broke the stream once the publisher's read finds it broken."""
        await self._lost.wait()
        self._lost.clear()
        assert self._lost_error is not None
        raise self._lost_error

    def _read_available(self) -> int:
        """Take every report the kernel holds into the decoder; the bytes read. A broken stream reads as nothing
        and is handed to the reconnection (`_until_lost`)."""
        stream = self._stream
        if stream is None:
            return 0
        received = 0
        try:
            while True:
                data = stream.recv(READ_CHUNK_BYTES)
                if not data:
                    raise EOFError("pigpiod closed the notification socket")
                self._unread += data
                received += len(data)
                if len(data) < READ_CHUNK_BYTES:  # that was all: no second call only to hear it would block
                    break
        except BlockingIOError:
            pass
        except (OSError, EOFError) as error:
            self._drain()
            self._close_stream()
            self._lost_error = error
            self._lost.set()
            return received
        self._drain()
        return received

    def _close_stream(self) -> None:
        """Stop reading the notification socket and close it (odometry degraded until the next stream)."""
        stream, self._stream = self._stream, None
        self._connected = False
        self._degraded = True
        if stream is None:
            return
        self._stop_watching(stream)
        stream.close()

    def _stop_watching(self, stream: socket.socket) -> None:
        edge, self._edge = self._edge, None
        if edge is not None:
            with contextlib.suppress(ValueError, OSError):  # already closed: nothing is watched any more
                asyncio.get_running_loop().remove_reader(stream.fileno())
            if not edge.done():
                edge.set_result(None)

    def _drain(self) -> None:
        """Decode every whole report read so far."""
        whole = len(self._unread) - len(self._unread) % REPORT_SIZE
        if whole:
            data = bytes(self._unread[:whole])
            del self._unread[:whole]
            self.decode(data)

    def decode(self, data: bytes) -> None:
        """Decode whole 12-byte reports (the bulk path; public for the benchmark)."""
        assert self._tick_clock is not None
        reports = decode_reports(data)
        self._reports += len(reports)
        lost = self._gaps.check(reports["seq"])
        flags = reports["flags"]
        changes = reports[flags == 0] if flags.any() else reports  # watchdog, alive, event reports carry no edge
        illegal = self._decoder.decode(self._tick_clock.unwrap(changes["tick"]), changes["level"])
        if lost or illegal:
            self._degraded = True

    async def _resync(self, link: PigpioLink) -> None:
        """Re-anchor the tick map now and then, on the otherwise idle command socket."""
        while True:
            await asyncio.sleep(RESYNC_PERIOD_S)
            before = self._clock()
            tick = await link.command(Cmd.TICK, unsigned=True)
            if self._tick_clock is not None:
                self._tick_clock.anchor(tick, (before + self._clock()) / 2)

    async def _publish(self, on_ticks: Callable[[WheelTicks], None]) -> None:
        """Read the reports and publish at the rate, on the shared grid; at rest, only on an edge or a keep-alive."""
        period = 1.0 / self._encoders.publish_rate_hz
        loop = asyncio.get_running_loop()
        deadline = next_tick(loop.time(), period)
        quiet = 0
        while True:
            if quiet >= IDLE_AFTER_QUIET and self._stream is not None:
                await self._until_edge(self._stream, IDLE_KEEPALIVE_S)
                deadline = next_tick(loop.time(), period)
            else:
                await sleep_until(deadline, loop)
                deadline += period
                if deadline <= loop.time():  # the loop stalled: back on the grid rather than a burst of publications
                    deadline = next_tick(loop.time(), period)
            self.wakeups += 1
            quiet = 0 if self._read_available() else quiet + 1
            on_ticks(self.snapshot())

    async def _until_edge(self, stream: socket.socket, timeout_s: float) -> None:
        """Wait until a report arrives on `stream` (or it closes), or `timeout_s` passes."""
        loop = asyncio.get_running_loop()
        self._edge = edge = loop.create_future()
        loop.add_reader(stream.fileno(), _wake, edge)
        try:
            await asyncio.wait([edge], timeout=timeout_s)
        finally:
            if self._edge is edge:
                self._stop_watching(stream)

    def snapshot(self) -> WheelTicks:
        """The wheel ticks now (of the reports read so far); clears the degraded flag once reported."""
        now = self._clock()
        if self._connected and self._tick_clock is not None:
            counts_per_s = self._speed.update(self._decoder, self._tick_clock.to_unwrapped(now))
            speeds = [v * self._radians_per_count for v in counts_per_s]
        else:
            speeds = [0.0] * len(self._wiring)
        degraded, self._degraded = self._degraded or not self._connected, False
        c = self._decoder.counts
        return WheelTicks(now, (c[0], c[1], c[2], c[3]), (speeds[0], speeds[1], speeds[2], speeds[3]), degraded)


def _wake(edge: asyncio.Future[None]) -> None:
    if not edge.done():
        edge.set_result(None)
