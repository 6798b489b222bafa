"""A virtual pigpiod: a TCP server speaking pigpio's socket protocol, for the real `pigpio` client and gpiozero.

Theory of operation: one asyncio server owns the sockets; a `PinBank` (drivers.sim.pin_model) holds the pins. The
command sockets read and change pins; a socket that sends NOIB becomes a notification socket and receives 12-byte
reports whenever a monitored bank-1 level changes. The simulator drives input pins in bulk with
`drive_levels(ticks, levels, mask)`: one numpy call turns a batch of level changes into one `bytes` of reports per
notification handle. Every public method is thread-safe (one lock around the pins and handles); socket writes always
happen on the server's loop, so reports keep their sequence order whichever thread drove them.

Two ways to run it: `start()`/`stop()` (or `with`) serve from a background thread with its own loop, for blocking
clients such as pigpio and gpiozero in the same process; `open()`/`aclose()` (or `async with`) serve on the running
loop, for asyncio programs such as `robotd vpigpiod`.

Virtual time: `tick()` is the monotonic clock in microseconds, 32 bits, wrapping as pigpio's does, offset so that
the first tick is `start_tick` (tests start near 2^32 to cross the wrap). The simulator stamps the edges it drives
with ticks of its own choosing, normally close to `tick()`; reports carry those ticks (plus the glitch delay).

Not modelled: pigpio's 5 us sampling (edges closer than 5 us are all reported, none merged or missed); PWM and servo
waveforms (a PWM pin reads 0, or 1 at full duty, and emits no edges); watchdogs, events, alive keep-alives, waves,
scripts, I2C, SPI, serial, files and shell (they answer PI_UNKNOWN_COMMAND); pipe notifications (NO answers
PI_NO_HANDLE: use NOIB); bank 2 inputs (GPIO 32-53 are never driven). The glitch filter treats the last change of
each `drive_levels` batch as steady. Reports are lost only on purpose (`lose_reports`) or when a consumer leaves
more than `send_buffer_limit` bytes unread, and then their sequence numbers are skipped as pigpiod skips them.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from types import TracebackType
from typing import Self

import numpy as np
import numpy.typing as npt

from drivers.pigpio_protocol import (
    Cmd,
    Command,
    CommandDecoder,
    Err,
    ProtocolError,
    encode_answer,
    encode_reports,
)
from drivers.sim.pin_model import BANK1, USER_GPIOS, PinBank, glitch_filter

PI4B_4GB = 0xC03111
"""Hardware revision of a Raspberry Pi 4 Model B, 4 GB, as HWVER answers it."""
PIGPIO_VERSION = 79
MAX_HANDLES = 32
U32 = npt.NDArray[np.uint32]


@dataclass(slots=True)
class _Notifier:
    """One notification handle opened with NOIB on a socket."""

    transport: asyncio.Transport
    mask: int = 0
    paused: bool = True
    seq: int = 0
    to_lose: int = 0
    pending: deque[bytes] = field(default_factory=deque)


class _Connection(asyncio.Protocol):
    """One client socket: commands in, answers out; after NOIB, reports out."""

    def __init__(self, server: VirtualPigpiod) -> None:
        self._server = server
        self._decoder = CommandDecoder()
        self.transport: asyncio.Transport | None = None
        self.handle: int | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        self._server._connections.add(self)

    def data_received(self, data: bytes) -> None:
        assert self.transport is not None
        try:
            commands = self._decoder.feed(data)
        except ProtocolError:
            self.transport.abort()  # a corrupt stream cannot be resynchronised
            return
        for command in commands:
            result = self._server._execute(command, self)
            # pigpio writes only reports on a notification socket once its handle is answered.
            if self.handle is None or command.cmd == Cmd.NOIB:
                self.transport.write(encode_answer(command, result))

    def connection_lost(self, _exc: Exception | None) -> None:
        self._server._connections.discard(self)
        if self.handle is not None:
            self._server._close_handle(self.handle)


class VirtualPigpiod:
    """pigpiod on loopback for tests and the virtual robot; see the module docstring for what it models."""

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 0,
        *,
        start_tick: int | None = None,
        hardware_revision: int = PI4B_4GB,
        send_buffer_limit: int = 4 << 20,
    ) -> None:
        self.host = host
        self._requested_port = port
        self.hardware_revision = hardware_revision
        self.send_buffer_limit = send_buffer_limit
        now_us = time.monotonic_ns() // 1000
        self._tick_offset = 0 if start_tick is None else (start_tick - now_us)
        self._lock = threading.Lock()
        self._pins = PinBank()
        self._notifiers: dict[int, _Notifier] = {}
        self._last_report_tick: int | None = None
        self._flush_scheduled = False
        self._connections: set[_Connection] = set()
        self._server: asyncio.Server | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self.port = 0
        self.reports_sent = 0
        self.reports_lost = 0

    # --- lifecycle ----------------------------------------------------------------------------------------------

    async def open(self) -> Self:
        """Start serving on the running loop; `port` is then the bound port."""
        self._loop = asyncio.get_running_loop()
        self._server = await self._loop.create_server(
            lambda: _Connection(self), self.host, self._requested_port, reuse_address=True
        )
        self.port = self._server.sockets[0].getsockname()[1]
        return self

    async def aclose(self) -> None:
        """Stop serving and close every client socket."""
        if self._server is not None:
            self._server.close()
            for connection in list(self._connections):
                if connection.transport is not None:
                    connection.transport.abort()
            await self._server.wait_closed()
            self._server = None

    def start(self, timeout_s: float = 5.0) -> Self:
        """Start serving from a background thread with its own loop; returns once the port is bound."""
        ready = threading.Event()
        failure: list[BaseException] = []

        def serve() -> None:
            loop = asyncio.new_event_loop()
            try:
                loop.run_until_complete(self.open())
            except OSError as error:
                failure.append(error)
                ready.set()
                loop.close()
                return
            ready.set()
            try:
                loop.run_forever()
                loop.run_until_complete(self.aclose())
            finally:
                loop.close()

        self._thread = threading.Thread(target=serve, name="vpigpiod", daemon=True)
        self._thread.start()
        if not ready.wait(timeout_s):
            raise TimeoutError("the virtual pigpiod did not start")
        if failure:
            self._thread.join()
            raise failure[0]
        return self

    def stop(self) -> None:
        """Stop a server started with `start()` and wait for its thread."""
        if self._thread is None or self._loop is None:
            return
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join()
        self._thread = None

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *_exc: object) -> None:
        self.stop()

    async def __aenter__(self) -> Self:
        return await self.open()

    async def __aexit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None
    ) -> None:
        await self.aclose()

    # --- the simulator's API ------------------------------------------------------------------------------------

    def tick(self) -> int:
        """The current virtual tick: microseconds, 32 bits, wrapping."""
        return (time.monotonic_ns() // 1000 + self._tick_offset) & BANK1

    def tick_at(self, monotonic_s: float) -> int:
        """The virtual tick at a time of the monotonic clock."""
        return (round(monotonic_s * 1e6) + self._tick_offset) & BANK1

    def ticks_at(self, monotonic_s: npt.ArrayLike) -> U32:
        """The virtual ticks at many times of the monotonic clock."""
        micros = np.round(np.asarray(monotonic_s, dtype=np.float64) * 1e6).astype(np.int64) + self._tick_offset
        return (micros & BANK1).astype(np.uint32)

    def drive_levels(self, ticks: npt.ArrayLike, levels: npt.ArrayLike, mask: int) -> None:
        """Drive the input pins of `mask` (bank 1): after the change at `ticks[i]` they read `levels[i]`.

        Ticks must not go backwards. Bits of `mask` on output pins are ignored (the client owns those).
        """
        tick_array = np.ascontiguousarray(ticks, dtype=np.uint32)
        level_array = np.ascontiguousarray(levels, dtype=np.uint32)
        if tick_array.ndim != 1 or tick_array.shape != level_array.shape:
            raise ValueError("ticks and levels must be 1-D arrays of the same length")
        with self._lock:
            mask &= BANK1 & ~self._pins.output_mask()
            if not mask or not len(tick_array):
                return
            previous = self._pins.bank1
            words = (level_array & np.uint32(mask)) | np.uint32(previous & ~mask)
            self._pins.levels = (self._pins.levels & ~BANK1) | int(words[-1])
            self._pins.driven |= mask
            steady = {gpio: us for gpio, us in enumerate(self._pins.glitch_us) if us and mask >> gpio & 1}
            self._report(*glitch_filter(tick_array, words, previous, steady), previous)

    def drive_edges(self, gpio: int, ticks: npt.ArrayLike, levels: npt.ArrayLike) -> None:
        """Drive one input pin: it takes `levels[i]` (0 or 1) at `ticks[i]`."""
        if not 0 <= gpio < USER_GPIOS:
            raise ValueError(f"only bank 1 (GPIO 0-31) can be driven, got {gpio}")
        bits = np.asarray(levels, dtype=np.uint32) << np.uint32(gpio)
        self.drive_levels(ticks, bits, 1 << gpio)

    def lose_reports(self, count: int) -> None:
        """Drop the next `count` reports of every notification handle, skipping their sequence numbers."""
        with self._lock:
            for notifier in self._notifiers.values():
                notifier.to_lose += count

    def level(self, gpio: int) -> int:
        """Level of a GPIO (0 or 1), as READ answers it."""
        with self._lock:
            return self._pins.level(gpio)

    def mode(self, gpio: int) -> int:
        """Mode of a GPIO as a pigpio number (0 input, 1 output, ...)."""
        with self._lock:
            return int(self._pins.modes[gpio])

    def pull(self, gpio: int) -> int:
        """Pull resistor of a GPIO (0 off, 1 down, 2 up)."""
        with self._lock:
            return int(self._pins.pulls[gpio])

    def pwm_duty(self, gpio: int) -> float:
        """Duty of a GPIO in [0, 1]: PWM duty / range, or the level of a plain output, 0 for an input."""
        with self._lock:
            return self._pins.pwm_fraction(gpio)

    def pwm_frequency(self, gpio: int) -> int:
        """PWM frequency of a GPIO in Hz."""
        with self._lock:
            return self._pins.pwm[gpio].frequency

    def glitch_filter_us(self, gpio: int) -> int:
        """Glitch filter of a GPIO in microseconds (0 = off)."""
        with self._lock:
            return self._pins.glitch_us[gpio]

    def notify_handles(self) -> dict[int, int]:
        """Open notification handles and the bank-1 mask each monitors (0 while paused)."""
        with self._lock:
            return {handle: 0 if n.paused else n.mask for handle, n in self._notifiers.items()}

    # --- commands -----------------------------------------------------------------------------------------------

    def _execute(self, command: Command, connection: _Connection) -> int:
        """Carry out one command from a socket (on the loop thread)."""
        with self._lock:
            match command.cmd:
                case Cmd.TICK:
                    return self.tick()
                case Cmd.HWVER:
                    return self.hardware_revision
                case Cmd.PIGPV:
                    return PIGPIO_VERSION
                case Cmd.NOIB:
                    return self._open_handle(connection)
                case Cmd.NO:
                    return Err.NO_HANDLE
                case Cmd.NB | Cmd.NP | Cmd.NC:
                    return self._notify_command(command)
            before = self._pins.bank1
            result = self._pins.execute(command)
            if self._pins.bank1 != before:  # a write or a pull change: report it like any edge
                tick = np.array([self.tick()], dtype=np.uint32)
                self._report(tick, np.array([self._pins.bank1], dtype=np.uint32), before)
            return result

    def _open_handle(self, connection: _Connection) -> int:
        free = next((h for h in range(MAX_HANDLES) if h not in self._notifiers), None)
        if free is None or connection.transport is None:
            return Err.NO_HANDLE
        self._notifiers[free] = _Notifier(connection.transport)
        connection.handle = free
        return free

    def _notify_command(self, command: Command) -> int:
        notifier = self._notifiers.get(command.p1)
        if notifier is None:
            return Err.BAD_HANDLE
        if command.cmd == Cmd.NB:
            notifier.mask, notifier.paused = command.p2, False
        elif command.cmd == Cmd.NP:
            notifier.paused = True
        else:
            del self._notifiers[command.p1]
            notifier.transport.close()  # pigpiod closes a NOIB socket with its handle
        return 0

    def _close_handle(self, handle: int) -> None:
        with self._lock:
            self._notifiers.pop(handle, None)

    # --- reports ------------------------------------------------------------------------------------------------

    def _report(self, ticks: U32, words: U32, previous: int) -> None:
        """Queue the reports of bank-1 changes for every handle monitoring a changed bit (lock held)."""
        if not len(ticks):
            return
        if self._last_report_tick is not None:
            # Glitch-delayed stamps may fall before the last report sent: hold them at it, keeping ticks ordered.
            since = (ticks - np.uint32(self._last_report_tick)).view(np.int32)
            ticks = (np.maximum.accumulate(np.maximum(since, 0)).astype(np.uint32) + self._last_report_tick).astype(
                np.uint32
            )
        self._last_report_tick = int(ticks[-1])
        changed = words ^ np.concatenate((np.array([previous], dtype=np.uint32), words[:-1]))
        for notifier in self._notifiers.values():
            if notifier.paused or not notifier.mask:
                continue
            selected = np.flatnonzero(changed & np.uint32(notifier.mask))
            count = len(selected)
            if not count:
                continue
            seq = ((notifier.seq + np.arange(count)) & 0xFFFF).astype(np.uint16)
            notifier.seq += count
            lose = min(notifier.to_lose, count)
            notifier.to_lose -= lose
            self.reports_lost += lose
            if lose < count:
                kept = selected[lose:]
                notifier.pending.append(encode_reports(seq[lose:], ticks[kept], words[kept]))
        if not self._flush_scheduled and self._loop is not None and any(n.pending for n in self._notifiers.values()):
            self._flush_scheduled = True
            with contextlib.suppress(RuntimeError):  # the loop is closing: nobody is left to read
                self._loop.call_soon_threadsafe(self._flush)

    def _flush(self) -> None:
        """Write queued reports to their sockets (on the loop thread)."""
        with self._lock:
            self._flush_scheduled = False
            for notifier in self._notifiers.values():
                if not notifier.pending:
                    continue
                data = b"".join(notifier.pending)
                notifier.pending.clear()
                if notifier.transport.is_closing():
                    continue
                count = len(data) // 12
                if notifier.transport.get_write_buffer_size() > self.send_buffer_limit:
                    self.reports_lost += count  # pigpiod drops what a slow reader cannot take
                    continue
                notifier.transport.write(data)
                self.reports_sent += count
