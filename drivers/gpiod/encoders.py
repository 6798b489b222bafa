"""Wheel encoders on a libgpiod v2 line request, read in bulk on the event loop (the Raspberry Pi 5 back-end).

Theory of operation: one request holds all eight encoder lines with both edges detected and a large kernel buffer.
Its file descriptor is watched with `loop.add_reader`; each time it is readable one `os.read` takes every event the
kernel holds (up to 1365 records of 48 bytes), and the bytes are gathered and decoded in batches by
drivers.gpiod.events (numpy, no Python per edge). A publisher task hands `WheelTicks`, the type the pigpio back-end
publishes, to the daemon at `publish_rate_hz`. No thread.

Time: event stamps are CLOCK_MONOTONIC nanoseconds, the clock `time.monotonic()` reads on Linux; they are mapped onto
the daemon's clock through one (kernel ns, daemon s) pair taken at open, which is exact for the real clock and keeps
an injected test clock consistent. Being the same clock, the pair never needs re-anchoring.

Losses: sequence-number gaps (the kernel's buffer overflowed) and illegal transitions mark the next publication
degraded, as pigpio's lost reports do. A request that fails (the fd reads an error or end of file) is released and
opened again with exponential backoff; meanwhile the counts hold, the speeds read 0 and `degraded` is true. An edge
that lands between opening the request and reading the lines' levels is taken as the starting level, not counted.
"""

from __future__ import annotations

import asyncio
import logging
import math
import os
import time
from collections.abc import Callable, Sequence

from drivers.gpiod.events import EVENT_SIZE, EdgeEventDecoder
from drivers.gpiod.lines import (
    EventLines,
    EventLineSettings,
    EventLinesOpener,
    GpioUnavailableError,
    open_event_lines,
)
from drivers.wheels.encoders import EncoderCounters, WheelTicks
from drivers.wheels.quadrature import Decoding, EdgeTimedSpeed, EncoderWiring

log = logging.getLogger("robotd.encoders")

READ_SIZE = (1 << 16) // EVENT_SIZE * EVENT_SIZE
"""One read: 1365 whole events, more than the kernel's largest buffer (1024)."""
DECODE_BATCH_BYTES = 5461 * EVENT_SIZE
"""Bytes gathered before decoding without waiting for the next publication: as many events as the pigpio back-end's
64 KiB of reports, so numpy's fixed cost per call is spread as thin."""


class KernelClock:
    """Maps CLOCK_MONOTONIC nanoseconds onto the daemon's monotonic seconds through one pair read together."""

    def __init__(self, kernel_ns: int, monotonic_s: float) -> None:
        self.kernel_ns = kernel_ns
        self.monotonic_s = monotonic_s

    def to_monotonic(self, timestamp_ns: int) -> float:
        """The daemon's time of a kernel timestamp."""
        return self.monotonic_s + (timestamp_ns - self.kernel_ns) * 1e-9

    def to_kernel_ns(self, monotonic_s: float) -> int:
        """The kernel timestamp of a daemon time."""
        return self.kernel_ns + round((monotonic_s - self.monotonic_s) * 1e9)


class GpiodEncoders:
    """Encoder source on a libgpiod v2 line request (see the module docstring); an `EncoderSource`."""

    def __init__(
        self,
        encoders: Sequence[EncoderWiring],
        counts_per_rev: int,
        *,
        decoding: Decoding = "x4",
        publish_rate_hz: float = 50.0,
        settings: EventLineSettings | None = None,
        open_lines: EventLinesOpener = open_event_lines,
        reopen_max_s: float = 5.0,
        clock: Callable[[], float] = time.monotonic,
        kernel_clock_ns: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        if len(encoders) != 4:
            raise ValueError(f"four encoders (FL, FR, RL, RR) are needed, got {len(encoders)}")
        self._wiring = list(encoders)
        self._offsets = sorted({line for e in self._wiring for line in (e.a, e.b)})
        if len(self._offsets) != 8:
            raise ValueError(f"the encoders' eight lines must be distinct, got {[(e.a, e.b) for e in self._wiring]}")
        self._decoding: Decoding = decoding
        self._radians_per_count = 2 * math.pi / counts_per_rev
        self._publish_period_s = 1.0 / publish_rate_hz
        self._settings = settings or EventLineSettings()
        self._open_lines = open_lines
        self._reopen_max_s = reopen_max_s
        self._clock = clock
        self._kernel_clock_ns = kernel_clock_ns
        self._decoder = EdgeEventDecoder(self._wiring, decoding, 0, 0)
        self._speed = self._new_speed()
        self._time = KernelClock(0, 0.0)
        self._unread = bytearray()
        self._lines: EventLines | None = None
        self._connected = False
        self._degraded = False
        self._reconnects = 0

    def _new_speed(self) -> EdgeTimedSpeed:
        return EdgeTimedSpeed(len(self._wiring), stale_after_us=round(2e6 * self._publish_period_s))

    @property
    def counters(self) -> EncoderCounters:
        """Health counters since start (events decoded and lost are the pigpio back-end's reports)."""
        i = [int(n) for n in self._decoder.quadrature.illegal]
        return EncoderCounters(self._decoder.events, self._decoder.lost, (i[0], i[1], i[2], i[3]), self._reconnects)

    @property
    def connected(self) -> bool:
        """True while the line request is open."""
        return self._connected

    @property
    def ticks(self) -> tuple[int, ...]:
        """The cumulative counts decoded so far, in wheel order."""
        return tuple(int(n) for n in self._decoder.quadrature.counts)

    async def run(self, on_ticks: Callable[[WheelTicks], None]) -> None:
        """Open the request (or raise GpioUnavailableError), then publish wheel ticks until cancelled."""
        await self._open()
        try:
            async with asyncio.TaskGroup() as tasks:
                tasks.create_task(self._publish(on_ticks), name="encoders-publish")
                tasks.create_task(self._stay_open(), name="encoders-events")
        finally:
            self._release()

    async def _open(self) -> None:
        lines = await asyncio.to_thread(self._open_lines, self._offsets, self._settings)
        try:
            os.set_blocking(lines.fd, False)  # a readable fd is read once per wake-up; never wait inside the loop
            levels = lines.levels()
        except BaseException:
            lines.release()
            raise
        self._lines = lines
        self.begin_request(levels, self._kernel_clock_ns(), self._clock())

    def _release(self) -> None:
        self._connected = False
        if self._lines is not None:
            lines, self._lines = self._lines, None
            lines.release()

    def begin_request(self, levels: int, kernel_ns: int, monotonic_s: float) -> None:
        """Start decoding a new request whose lines read `levels` at `kernel_ns` (CLOCK_MONOTONIC) = `monotonic_s`.

        Its sequence numbers restart and its edge times start a new time line; counts carry on.
        """
        self._unread.clear()
        self._time = KernelClock(kernel_ns, monotonic_s)
        self._decoder.restart(levels, kernel_ns)
        self._speed = self._new_speed()
        self._connected = True

    async def _stay_open(self) -> None:
        """Read the request's events; when it fails, open it again with backoff."""
        backoff = 0.05
        while True:
            assert self._lines is not None
            try:
                await self._read(self._lines.fd)
            except (OSError, EOFError) as error:
                log.warning("encoder events lost (%s): odometry degraded, requesting the lines again", error)
            finally:
                self._drain()  # what arrived before the failure still counts
                self._degraded = True
                self._release()
            while True:
                await asyncio.sleep(backoff)
                backoff = min(backoff * 2, self._reopen_max_s)
                try:
                    await self._open()
                except OSError as error:  # GpioUnavailableError is one
                    log.debug("encoders: lines still unavailable: %s", error)
                    continue
                self._reconnects += 1
                backoff = 0.05
                log.info("encoder events restored")
                break

    async def _read(self, fd: int) -> None:
        """Gather events as the fd becomes readable until it fails; decode in batches of DECODE_BATCH_BYTES."""
        loop = asyncio.get_running_loop()
        failed: asyncio.Future[BaseException] = loop.create_future()

        def readable() -> None:
            failure: BaseException
            try:
                data = os.read(fd, READ_SIZE)
            except BlockingIOError:
                return
            except OSError as error:
                data, failure = b"", error
            else:
                failure = EOFError("the line request's file descriptor reached its end")
            if not data:
                loop.remove_reader(fd)
                if not failed.done():
                    failed.set_result(failure)
                return
            self._unread += data
            if len(self._unread) >= DECODE_BATCH_BYTES:
                self._drain()

        loop.add_reader(fd, readable)
        try:
            raise await failed
        finally:
            loop.remove_reader(fd)

    def _drain(self) -> None:
        """Decode everything read so far, or what the decoder held back at the previous drain."""
        if self._unread:
            data = bytes(self._unread)
            self._unread.clear()
            self.decode(data)
        elif self._decoder.holding:
            self.decode(b"")

    def decode(self, data: bytes) -> None:
        """Decode raw event records (the bulk path; public for the benchmark)."""
        illegal_before = sum(self._decoder.quadrature.illegal)
        lost = self._decoder.feed(data) if data else self._decoder.flush()
        if lost or sum(self._decoder.quadrature.illegal) != illegal_before:
            self._degraded = True

    async def _publish(self, on_ticks: Callable[[WheelTicks], None]) -> None:
        loop = asyncio.get_running_loop()
        deadline = loop.time()
        while True:
            deadline += self._publish_period_s
            await asyncio.sleep(max(0.0, deadline - loop.time()))
            on_ticks(self.snapshot())

    def snapshot(self) -> WheelTicks:
        """The wheel ticks now; clears the degraded flag once reported."""
        if self._connected:
            self._drain()
        now = self._clock()
        if self._connected:
            now_us = self._decoder.to_ticks_us(self._time.to_kernel_ns(now))
            speeds = [v * self._radians_per_count for v in self._speed.update(self._decoder.quadrature, now_us)]
        else:
            speeds = [0.0] * len(self._wiring)
        degraded, self._degraded = self._degraded or not self._connected, False
        c = self._decoder.quadrature.counts
        return WheelTicks(now, (c[0], c[1], c[2], c[3]), (speeds[0], speeds[1], speeds[2], speeds[3]), degraded)


__all__ = ["GpioUnavailableError", "GpiodEncoders", "KernelClock"]
