"""A virtual pigpiod: a TCP server speaking pigpio's socket protocol, for the real `pigpio` client and gpiozero.

Theory of operation: one asyncio server owns the sockets; a `PinBank` (drivers.virtual.pins) holds the pins. The
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

Scripts (PROC, PROCR, PROCU, PROCP, PROCS, PROCD) run on the server's loop in real time: drivers.virtual.script_runner
says how, drivers.virtual.script_language which instructions are modelled. A command that must wait (PROCD while its
script finishes a delay) holds back the answers to the commands after it on its socket, as pigpiod's socket thread
does. Every write to a pin (mode, pull, level, PWM duty or range, bank writes), from a socket or a script, is kept
in a bounded history with its time and source (`pin_history`), for tests of write sequences.

Not modelled: pigpio's 5 us sampling (edges closer than 5 us are all reported, none merged or missed); PWM and servo
waveforms (a PWM pin reads 0, or 1 at full duty, and emits no edges); watchdogs, events, alive keep-alives, waves,
I2C, SPI, serial, files, shell, and MILS/MICS sent over a socket (they answer PI_UNKNOWN_COMMAND); pipe
notifications (NO answers PI_NO_HANDLE: use NOIB); bank 2 inputs (GPIO 32-53 are never driven). The glitch filter
treats the last change of each `drive_levels` batch as steady. Reports are lost only on purpose (`lose_reports`) or
when a consumer leaves more than `send_buffer_limit` bytes unread, and then their sequence numbers are skipped as
pigpiod skips them (drivers.virtual.notify_handles).
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import threading
import time
from collections import deque
from types import TracebackType
from typing import Self

import numpy as np
import numpy.typing as npt

from drivers.pigpiod.protocol import (
    Cmd,
    Command,
    CommandDecoder,
    Err,
    ProtocolError,
    encode_answer,
)
from drivers.virtual.notify_handles import NotifyHandles
from drivers.virtual.pins import BANK1, USER_GPIOS, PinBank, PinWrite, glitch_filter
from drivers.virtual.script_runner import ScriptHost

PI4B_4GB = 0xC03111
"""Hardware revision of a Raspberry Pi 4 Model B, 4 GB, as HWVER answers it."""
PIGPIO_VERSION = 79
U32 = npt.NDArray[np.uint32]
Reply = int | tuple[int, bytes] | asyncio.Future[int]
"""A command's result; with the data that follows the answer; or a result still to come."""
_SCRIPT_COMMANDS = frozenset({Cmd.PROC, Cmd.PROCR, Cmd.PROCU, Cmd.PROCP, Cmd.PROCS, Cmd.PROCD})


class _Connection(asyncio.Protocol):
    """One client socket: commands in, answers out; after NOIB, reports out."""

    def __init__(self, server: VirtualPigpiod) -> None:
        self._server = server
        self._decoder = CommandDecoder()
        self._queue: deque[Command] = deque()
        self._waiting = False
        self.transport: asyncio.Transport | None = None
        self.handle: int | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        if not self._server.serving:
            # accepted just before the server closed, connected just after: aclose aborted the others already
            transport.abort()
            return
        self._server._connections.add(self)

    def data_received(self, data: bytes) -> None:
        assert self.transport is not None
        try:
            commands = self._decoder.feed(data)
        except ProtocolError:
            self.transport.abort()  # a corrupt stream cannot be resynchronised
            return
        self._queue.extend(commands)
        self._serve()

    def _serve(self) -> None:
        """Answer queued commands in order; one whose result is still to come holds back those after it."""
        while self._queue and not self._waiting:
            command = self._queue.popleft()
            reply = self._server._execute(command, self)
            if isinstance(reply, asyncio.Future):
                self._waiting = True
                reply.add_done_callback(functools.partial(self._resume, command))
                return
            self._answer(command, reply)

    def _resume(self, command: Command, done: asyncio.Future[int]) -> None:
        self._waiting = False
        if done.cancelled() or self.transport is None or self.transport.is_closing():
            return
        self._answer(command, done.result())
        self._serve()

    def _answer(self, command: Command, reply: int | tuple[int, bytes]) -> None:
        assert self.transport is not None
        result, data = reply if isinstance(reply, tuple) else (reply, b"")
        # pigpio writes only reports on a notification socket once its handle is answered.
        if self.handle is None or command.cmd == Cmd.NOIB:
            self.transport.write(encode_answer(command, result) + data)

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
        history_limit: int = 50_000,
    ) -> None:
        self.host = host
        self._requested_port = port
        self.hardware_revision = hardware_revision
        now_us = time.monotonic_ns() // 1000
        self._tick_offset = 0 if start_tick is None else (start_tick - now_us)
        self._lock = threading.Lock()
        self._pins = PinBank()
        self._notify = NotifyHandles(send_buffer_limit)
        self._connections: set[_Connection] = set()
        self._scripts = ScriptHost(self._script_command)
        self._history: deque[PinWrite] = deque(maxlen=history_limit)
        self._server: asyncio.Server | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self.port = 0

    # --- lifecycle ----------------------------------------------------------------------------------------------

    async def open(self) -> Self:
        """Start serving on the running loop; `port` is then the bound port."""
        self._loop = asyncio.get_running_loop()
        self._server = await self._loop.create_server(
            lambda: _Connection(self), self.host, self._requested_port, reuse_address=True
        )
        self.port = self._server.sockets[0].getsockname()[1]
        return self

    @property
    def serving(self) -> bool:
        """Whether the server accepts connections (False once aclose has begun)."""
        return self._server is not None and self._server.is_serving()

    async def aclose(self) -> None:
        """Stop serving and close every client socket."""
        if self._server is not None:
            self._server.close()
            for connection in list(self._connections):
                if connection.transport is not None:
                    connection.transport.abort()
            await self._scripts.aclose()
            await self._server.wait_closed()
            # abort() closes each socket in a callback of a later loop pass: run those passes before the loop stops
            # (a socket left to the garbage collector is a ResourceWarning in whichever test comes next)
            for _ in range(3):
                await asyncio.sleep(0)
            self._server = None

    def start(self, timeout_s: float = 5.0) -> Self:
        """Start serving from a background thread with its own loop; returns once the port is bound."""
        ready = threading.Event()
        failure: list[BaseException] = []

        def serve() -> None:
            # asyncio.Runner: on the way out it cancels and finishes the loop's last tasks (a connection accepted as
            # the server closed) before closing the loop, so no socket is left to the garbage collector
            with asyncio.Runner() as runner:
                try:
                    runner.run(self.open())
                except OSError as error:
                    failure.append(error)
                    ready.set()
                    return
                ready.set()
                runner.get_loop().run_forever()
                runner.run(self.aclose())

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

    @property
    def reports_sent(self) -> int:
        """Notification reports written to sockets so far."""
        return self._notify.reports_sent

    @property
    def reports_lost(self) -> int:
        """Notification reports lost on purpose or dropped for a slow reader so far."""
        return self._notify.reports_lost

    def lose_reports(self, count: int) -> None:
        """Drop the next `count` reports of every notification handle, skipping their sequence numbers."""
        with self._lock:
            self._notify.lose(count)

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

    def pin_history(self, gpios: set[int] | None = None) -> list[PinWrite]:
        """The writes kept so far (oldest first; the oldest are dropped beyond `history_limit`), of some GPIOs."""
        with self._lock:
            return [write for write in self._history if gpios is None or write.gpio in gpios]

    def clear_pin_history(self) -> None:
        """Forget the writes kept so far."""
        with self._lock:
            self._history.clear()

    def notify_handles(self) -> dict[int, int]:
        """Open notification handles and the bank-1 mask each monitors (0 while paused)."""
        with self._lock:
            return self._notify.monitored()

    # --- commands -----------------------------------------------------------------------------------------------

    def _execute(self, command: Command, connection: _Connection) -> Reply:
        """Carry out one command from a socket (on the loop thread)."""
        if command.cmd in _SCRIPT_COMMANDS:
            return self._script_table_command(command)
        with self._lock:
            about = self._about_itself(command.cmd)
            if about is not None:
                return about
            match command.cmd:
                case Cmd.NOIB:
                    return self._open_handle(connection)
                case Cmd.NO:
                    return Err.NO_HANDLE
                case Cmd.NB | Cmd.NP | Cmd.NC:
                    return self._notify.command(command)
            return self._pin_command(command, "socket")

    def _script_table_command(self, command: Command) -> Reply:
        scripts, script_id = self._scripts, command.p1
        match command.cmd:
            case Cmd.PROC:
                return scripts.store(command.extension)
            case Cmd.PROCR:
                return scripts.run(script_id, command.extension)
            case Cmd.PROCU:
                return scripts.update(script_id, command.extension)
            case Cmd.PROCP:
                return scripts.status(script_id)
            case Cmd.PROCS:
                return scripts.stop(script_id)
        return scripts.delete(script_id)

    def _script_command(self, command: Command, source: str) -> int:
        """A socket command run by a script."""
        with self._lock:
            about = self._about_itself(command.cmd)
            return about if about is not None else self._pin_command(command, source)

    def _about_itself(self, cmd: int) -> int | None:
        """TICK, HWVER and PIGPV: what pigpiod says of itself, from a socket or a script (lock held); else None."""
        match cmd:
            case Cmd.TICK:
                return self.tick()
            case Cmd.HWVER:
                return self.hardware_revision
            case Cmd.PIGPV:
                return PIGPIO_VERSION
        return None

    def _pin_command(self, command: Command, source: str) -> int:
        """Run a pin command, keep its writes in the history and report level changes (lock held)."""
        before = self._pins.bank1
        written = self._pins.written_gpios(command)
        result = self._pins.execute(command)
        if result >= 0 and written:
            now, name = time.monotonic(), Cmd(command.cmd).name
            self._history.extend(self._pins.write_record(gpio, now, source, name) for gpio in written)
        if self._pins.bank1 != before:  # a write or a pull change: report it like any edge
            tick = np.array([self.tick()], dtype=np.uint32)
            self._report(tick, np.array([self._pins.bank1], dtype=np.uint32), before)
        return result

    def _open_handle(self, connection: _Connection) -> int:
        if connection.transport is None:
            return Err.NO_HANDLE
        handle = self._notify.open(connection.transport)
        if handle >= 0:
            connection.handle = handle
        return handle

    def _close_handle(self, handle: int) -> None:
        with self._lock:
            self._notify.close(handle)

    def _report(self, ticks: U32, words: U32, previous: int) -> None:
        """Queue the reports of bank-1 changes and have them written on the loop (lock held)."""
        if self._notify.report(ticks, words, previous) and self._loop is not None:
            with contextlib.suppress(RuntimeError):  # the loop is closing: nobody is left to read
                self._loop.call_soon_threadsafe(self._flush)

    def _flush(self) -> None:
        with self._lock:
            self._notify.flush()
