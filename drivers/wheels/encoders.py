"""Wheel encoders read from pigpiod's notification stream in bulk on the event loop.

Theory of operation: `PigpioEncoders` configures the encoder pins over a command socket (input, pull, glitch
filter), opens a second socket with NOIB and starts notifications (NB) for the eight pins. pigpiod then writes a
12-byte report per level change; each read from the socket takes whatever has arrived (hundreds of reports at
speed) and hands the batch to numpy: sequence gaps counted, ticks unwrapped, quadrature decoded
(drivers.wheels.quadrature). A publisher task hands `WheelTicks` to the daemon at `publish_rate_hz`. No thread, no
Python per edge.

Connection policy: the first connection failing raises `PigpiodUnavailableError` (a wrong host or a stopped pigpiod is
a configuration problem to report at once). A connection lost later is retried with exponential backoff up to
`pigpiod.reconnect_max_s`; meanwhile and for the first publication after it, `degraded` is true, the counts keep
their last values and the speeds read 0. Edges during the outage are lost: the odometry says so, never guesses.

Back-end seam: the daemon depends only on `EncoderSource` (and `WheelTicks`); an lgpio back-end for the Pi 5 and
Raspberry Pi OS 13, where pigpio does not run, would be a second class with the same `run()`.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from drivers.backoff import Backoff
from drivers.pigpiod.client import PigpioCommandError, PigpiodUnavailableError, PigpioLink, open_notifications
from drivers.pigpiod.notifications import SequenceGaps, TickClock
from drivers.pigpiod.protocol import REPORT_SIZE, Cmd, Mode, Pull, decode_reports
from drivers.settings import EncoderSettings, PigpiodAddress, in_wheel_order
from drivers.wheels.quadrature import EdgeTimedSpeed, EncoderWiring, QuadratureDecoder

log = logging.getLogger("robotd.encoders")

DECODE_BATCH_BYTES = 1 << 16
"""Reports gathered before decoding without waiting for the next publication (5461 reports)."""
RESYNC_PERIOD_S = 5.0
FIRST_RETRY_S = 0.05
"""How often the tick-to-monotonic map is re-anchored (follows drift between pigpio's and the kernel's clocks)."""


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
        link, notifications = await self._connect()
        async with asyncio.TaskGroup() as tasks:
            tasks.create_task(self._publish(on_ticks), name="encoders-publish")
            tasks.create_task(self._stay_connected(link, notifications), name="encoders-stream")

    async def _connect(self) -> tuple[PigpioLink, tuple[int, asyncio.StreamReader, asyncio.StreamWriter]]:
        """Configure the pins and start notifications; returns the command link and the notification socket."""
        host, port, timeout = self._pigpiod.host, self._pigpiod.port, self._pigpiod.connect_timeout_s
        link = await PigpioLink.connect(host, port, timeout)
        try:
            for encoder in self._wiring:
                for gpio in (encoder.a, encoder.b):
                    await link.command(Cmd.MODES, gpio, Mode.INPUT)
                    await link.command(Cmd.PUD, gpio, _PULLS[self._encoders.pull])
                    await link.command(Cmd.FG, gpio, self._encoders.glitch_filter_us)
            notifications = await open_notifications(host, port, timeout)
            levels = await link.command(Cmd.BR1, unsigned=True)
            before = self._clock()
            tick = await link.command(Cmd.TICK, unsigned=True)
            self.begin_stream(levels, tick, (before + self._clock()) / 2)
            await link.command(Cmd.NB, notifications[0], self._mask)
        except BaseException:
            self._connected = False
            await link.close()
            raise
        return link, notifications

    def begin_stream(self, levels: int, tick: int, monotonic_s: float) -> None:
        """Start decoding a new stream from bank-1 `levels`, with `tick` read at `monotonic_s`.

        Its sequence restarts and its edge times start a new time line; counts carry on.
        """
        self._unread.clear()
        self._decoder.restart(levels)
        self._gaps.restart()
        self._tick_clock = TickClock(tick, monotonic_s)
        self._speed = EdgeTimedSpeed(len(self._wiring), stale_after_us=self._stale_after_us())
        self._connected = True

    async def _stay_connected(
        self, link: PigpioLink, notifications: tuple[int, asyncio.StreamReader, asyncio.StreamWriter]
    ) -> None:
        """Read the stream; when it breaks, reconnect with backoff."""
        backoff = Backoff(FIRST_RETRY_S, self._pigpiod.reconnect_max_s)
        while True:
            try:
                async with asyncio.TaskGroup() as tasks:
                    tasks.create_task(self._read(notifications[1]))
                    tasks.create_task(self._resync(link))
            except* (OSError, EOFError, asyncio.IncompleteReadError) as group:
                log.warning(
                    "encoder stream from pigpiod lost (%s): odometry degraded, reconnecting", group.exceptions[0]
                )
            finally:
                self._drain()  # what arrived before the break still counts
                self._connected = False
                self._degraded = True
                notifications[2].close()
                await link.close()
            while True:
                await asyncio.sleep(backoff.next_delay())
                try:
                    # bounded as a whole: a pigpiod that accepts but stalls must not hold the encoders forever
                    async with asyncio.timeout(4 * self._pigpiod.connect_timeout_s):
                        link, notifications = await self._connect()
                except (PigpiodUnavailableError, OSError, PigpioCommandError) as error:
                    log.debug("encoders: pigpiod still unavailable: %s", error)
                    continue
                self._reconnects += 1
                backoff.reset()
                log.info("encoder stream from pigpiod restored")
                break

    async def _read(self, reader: asyncio.StreamReader) -> None:
        """Take reports off the socket as they arrive; decode them in batches of DECODE_BATCH_BYTES or at publication.

        pigpiod flushes notifications every millisecond; decoding each small read would pay numpy's fixed cost per
        call a thousand times a second, so reads are only gathered here.
        """
        while True:
            data = await reader.read(DECODE_BATCH_BYTES)
            if not data:
                raise EOFError("pigpiod closed the notification socket")
            self._unread += data
            if len(self._unread) >= DECODE_BATCH_BYTES:
                self._drain()

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
        illegal_before = int(self._decoder.illegal.sum())
        flags = reports["flags"]
        changes = reports[flags == 0] if flags.any() else reports  # watchdog, alive, event reports carry no edge
        self._decoder.decode(self._tick_clock.unwrap(changes["tick"]), changes["level"].astype(np.uint32))
        if lost or int(self._decoder.illegal.sum()) != illegal_before:
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
        period = 1.0 / self._encoders.publish_rate_hz
        loop = asyncio.get_running_loop()
        deadline = loop.time()
        while True:
            deadline += period
            await asyncio.sleep(max(0.0, deadline - loop.time()))
            on_ticks(self.snapshot())

    def snapshot(self) -> WheelTicks:
        """The wheel ticks now; clears the degraded flag once reported."""
        if self._connected:
            self._drain()
        now = self._clock()
        if self._connected and self._tick_clock is not None:
            speeds = self._speed.update(self._decoder, self._tick_clock.to_unwrapped(now)) * self._radians_per_count
        else:
            speeds = np.zeros(len(self._wiring))
        degraded, self._degraded = self._degraded or not self._connected, False
        c = self._decoder.counts
        s = [float(v) for v in speeds]
        return WheelTicks(now, (int(c[0]), int(c[1]), int(c[2]), int(c[3])), (s[0], s[1], s[2], s[3]), degraded)
