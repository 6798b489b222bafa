"""The Marvelmind serial reader: a thin asyncio adapter that opens the port, feeds the parser and reconnects.

Theory of operation: one `run()` task loops over connection attempts. The device path comes from the configuration
(a plain path, a /dev/serial/by-id/... link or a glob, first sorted match) and is resolved again on every attempt,
because a beacon that resets or sleeps comes back under another ttyACM number. pyserial-asyncio-fast opens the port
in an executor, so the loop never blocks. Bytes are stamped with `clock()` as they are read and fed to the sans-I/O
`MarvelmindParser`; its events go to `on_event`. The reader never writes to the port: any request stops the
beacon's stream for 5 s. When the device vanishes (unplug, reset, sleep) it reopens it with a capped exponential
backoff, logging the outage once when it starts and once when it ends, never once per attempt.

Two guards sit at this edge, before any event reaches the daemon. Under `hedgehog_address: auto` a reopened port may
hold another hedgehog: the parser learns the address again from its first position frame (and re-latches by itself
when the port stays open and our hedgehog falls silent while another streams); each change of address is logged once
at INFO, old and new. A fix outside the map (drivers.marvelmind.mapbound: configured bounds, or the stationary
beacons' box and a margin) is refused and counted as `outside_map`, never handed on: fused, it could re-seed the pose
of a filter that has been rejecting fixes. The first refusal of a run is logged at WARNING, the end of the run at INFO.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import glob
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import serial
import serial_asyncio_fast

from drivers.backoff import Backoff
from drivers.marvelmind.events import Counters, Event, Position, StationaryBeacons
from drivers.marvelmind.mapbound import MapBound
from drivers.marvelmind.protocol import MarvelmindParser
from drivers.settings import MarvelmindSettings

logger = logging.getLogger("robotd.marvelmind")

CLOSE_TIMEOUT_S = 1.0
FIRST_RETRY_S = 0.05  # a pseudo-terminal or a USB re-enumeration is usually back within tens of ms


class LinkState(enum.Enum):
    """Where the reader is in its connection cycle."""

    CONNECTING = "connecting"  # never connected yet
    STREAMING = "streaming"
    LOST = "lost"  # was streaming; the device vanished and is being reopened


@dataclass(frozen=True, slots=True)
class MarvelmindHealth:
    """The reader's health at one instant."""

    state: LinkState
    connected: bool
    stale: bool  # no valid fix for longer than stale_after_s (or never one)
    device: str | None  # the path that is (or was last) open


def resolve_device(pattern: str) -> str | None:
    """The device path to open: the pattern itself, or the first sorted match of a glob (None when none matches)."""
    if not glob.has_magic(pattern):
        return pattern
    matches = sorted(glob.glob(pattern))
    return matches[0] if matches else None


class _SerialStream(asyncio.Protocol):
    """Receives the port's bytes for one connection; `closed` resolves when the connection ends."""

    def __init__(self, on_bytes: Callable[[bytes], None]) -> None:
        self._on_bytes = on_bytes
        self.closed: asyncio.Future[Exception | None] = asyncio.get_running_loop().create_future()

    def data_received(self, data: bytes) -> None:
        try:
            self._on_bytes(data)
        except Exception as error:  # noqa: BLE001 - re-raised by run(): a consumer's bug must not vanish in the loop
            if not self.closed.done():
                self.closed.set_exception(error)

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.closed.done():
            self.closed.set_result(exc)


class MarvelmindReader:
    """Streams events from a Marvelmind hedgehog on a serial port until cancelled, reconnecting when it vanishes."""

    def __init__(
        self,
        config: MarvelmindSettings,
        on_event: Callable[[Event], None],
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.config = config
        self.parser = MarvelmindParser(config.hedgehog_address, config.default_latency_s, config.relatch_after_s)
        self.map = MapBound(config.map_bounds_m, config.map_margin_m)
        self._on_event = on_event
        self._clock = clock
        self._state = LinkState.CONNECTING
        self._device: str | None = None
        self._last_fix_arrival: float | None = None
        self._outage_since: float | None = None
        self._address: int | None = None  # under auto: the hedgehog address last logged as followed
        self._reopened = False  # the port was reopened since the address was last seen
        self._refused_run = 0  # consecutive fixes refused as outside the map
        self.reconnections = 0

    @property
    def counters(self) -> Counters:
        """The parser's counters (frames by code, CRC failures, junk bytes, ...)."""
        return self.parser.counters

    def health(self, now: float | None = None) -> MarvelmindHealth:
        """Connected? Stale (no valid fix arrived within stale_after_s)? At `now` (default: the reader's clock)."""
        now = self._clock() if now is None else now
        age = None if self._last_fix_arrival is None else now - self._last_fix_arrival
        return MarvelmindHealth(
            state=self._state,
            connected=self._state is LinkState.STREAMING,
            stale=age is None or age > self.config.stale_after_s,
            device=self._device,
        )

    async def run(self) -> None:
        """Read the port until cancelled; reopen it with capped backoff whenever it vanishes or cannot be opened."""
        backoff = Backoff(FIRST_RETRY_S, self.config.reconnect_max_s)
        while True:
            try:
                path, transport, stream = await self._open()
            except (OSError, serial.SerialException) as error:
                self._note_outage(f"cannot open {self.config.device}: {error}")
                await asyncio.sleep(backoff.next_delay())
                continue
            self._note_streaming(path)
            backoff.reset()
            try:
                reason = await stream.closed
            finally:
                await self._close(transport, stream)  # on cancellation too: the port is never left open
            self._note_outage(f"{path} vanished: {reason or 'closed'}")
            self._state = LinkState.LOST
            self.parser.finish()  # a frame cut by the outage is junk, not the start of the next connection's
            self.parser.forget_address()  # under auto: what is plugged in next may be another hedgehog
            self._reopened = True

    async def _open(self) -> tuple[str, Any, _SerialStream]:
        path = resolve_device(self.config.device)
        if path is None:
            raise FileNotFoundError(f"no device matches {self.config.device!r}")
        stream = _SerialStream(self._on_bytes)
        transport, _ = await serial_asyncio_fast.create_serial_connection(
            asyncio.get_running_loop(), lambda: stream, path, baudrate=self.config.baudrate
        )
        return path, transport, stream

    @staticmethod
    async def _close(transport: Any, stream: _SerialStream) -> None:
        """Close the port and wait until it is closed (the transport closes it in an executor)."""
        transport.close()
        with contextlib.suppress(Exception):  # the reason the connection ended was already taken from `closed`
            async with asyncio.timeout(CLOSE_TIMEOUT_S):  # not wait_for: 3.11's can drop a cancellation
                await asyncio.shield(stream.closed)

    def _on_bytes(self, data: bytes) -> None:
        arrival = self._clock()
        events = self.parser.feed(data, arrival)
        address = self.parser.hedgehog_address
        if address is not None and self.parser.auto:
            if address != self._address:
                self._note_address(address)
            self._reopened = False
        for event in events:
            if isinstance(event, Position):
                if not self.map.admits(event.x, event.y):
                    self._note_outside_map(event)
                    continue
                if self._refused_run:
                    logger.info("marvelmind: fixes inside the map again after %d refused", self._refused_run)
                    self._refused_run = 0
                self._last_fix_arrival = event.arrival
            elif isinstance(event, StationaryBeacons):
                self.map.on_beacons(event)
            self._on_event(event)

    def _note_address(self, address: int) -> None:
        """One INFO line per hedgehog address learnt under auto: the first, and each change, with the old one."""
        if self._address is None:
            logger.info("marvelmind: following hedgehog address %d (auto)", address)
        else:
            why = (
                "the port was reopened"
                if self._reopened
                else f"{self._address} sent no position for {self.config.relatch_after_s:g} s while {address} did"
            )
            logger.info(
                "marvelmind: following hedgehog address %d instead of %d (auto: %s)", address, self._address, why
            )
        self._address = address

    def _note_outside_map(self, fix: Position) -> None:
        self.parser.counters.outside_map += 1
        self._refused_run += 1
        if self._refused_run == 1:
            box = self.map.box
            assert box is not None
            logger.warning(
                "marvelmind: fix (%.2f, %.2f) m is outside the map x %.2f..%.2f, y %.2f..%.2f m: refused",
                fix.x, fix.y, box[0], box[2], box[1], box[3],
            )  # fmt: skip

    def _note_outage(self, reason: str) -> None:
        if self._outage_since is None:  # once per outage, not once per attempt
            self._outage_since = self._clock()
            logger.warning("marvelmind: %s; retrying every <= %.1f s", reason, self.config.reconnect_max_s)
        else:
            logger.debug("marvelmind: %s", reason)

    def _note_streaming(self, path: str) -> None:
        if self._outage_since is not None:
            logger.info("marvelmind: streaming from %s after %.2f s", path, self._clock() - self._outage_since)
            if self._state is LinkState.LOST:
                self.reconnections += 1
        else:
            logger.info("marvelmind: streaming from %s", path)
        self._outage_since = None
        self._device = path
        self._state = LinkState.STREAMING
