"""A small asyncio client of pigpiod's socket: commands answered one at a time or sent without waiting, and
notification sockets.

robotd's encoder source and motor deadman talk to pigpiod with this instead of the `pigpio` library, whose blocking
calls and callback thread do not belong on the event loop.
"""

from __future__ import annotations

import asyncio
import contextlib
import select
import socket
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from drivers.pigpiod.protocol import (
    COMMAND,
    EXTENDED_ANSWERS,
    Cmd,
    Err,
    decode_result,
    encode_command,
    signed_result,
)


class PigpiodUnavailableError(ConnectionError):
    """pigpiod does not answer at the configured host and port."""

    def __init__(self, host: str, port: int, reason: object) -> None:
        super().__init__(
            f"pigpiod is not reachable at {host}:{port} ({reason}); is it running? "
            "On the robot: sudo systemctl start pigpiod; in simulation: robotd vpigpiod --port "
            f"{port}"
        )
        self.host, self.port = host, port


class PigpioCommandError(Exception):
    """pigpiod refused a command."""

    def __init__(self, cmd: int, p1: int, p2: int, code: int) -> None:
        name = Err(code).name if code in Err._value2member_map_ else "error"
        command = Cmd(cmd).name if cmd in Cmd._value2member_map_ else str(cmd)
        super().__init__(f"pigpiod refused {command}({p1}, {p2}): {name} ({code})")
        self.code = code


async def _open(host: str, port: int, timeout_s: float) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    try:
        async with asyncio.timeout(timeout_s):  # not wait_for: Python 3.11's can drop a cancellation
            reader, writer = await asyncio.open_connection(host, port)
    except (OSError, TimeoutError) as error:
        raise PigpiodUnavailableError(host, port, error or "timed out") from error
    sock = writer.get_extra_info("socket")
    if sock is not None:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # commands are tiny and wait for their answer
    return reader, writer


@dataclass(frozen=True, slots=True)
class Answer:
    """pigpiod's answer to one command: the command it answers, its signed result, the data after it if any."""

    cmd: int
    result: int
    data: bytes = b""


class PigpioLink:
    """A command socket to pigpiod.

    Either one command at a time (`command`, `query`: each waits for its answer), or commands sent without waiting
    (`post`) whose answers the owner reads in order (`read_answer`); not both at once on one link.
    """

    def __init__(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, host: str, port: int, timeout_s: float
    ) -> None:
        self._reader, self._writer = reader, writer
        self._lock = asyncio.Lock()
        self.host, self.port = host, port
        self.timeout_s = timeout_s

    @classmethod
    async def connect(cls, host: str, port: int, timeout_s: float) -> PigpioLink:
        """Connect, or raise PigpiodUnavailableError; `timeout_s` also bounds each command's answer."""
        reader, writer = await _open(host, port, timeout_s)
        return cls(reader, writer, host, port, timeout_s)

    async def command(
        self, cmd: int, p1: int = 0, p2: int = 0, *, extension: bytes = b"", unsigned: bool = False
    ) -> int:
        """Send one command (with its extension, if any) and return its result; a negative one raises
        PigpioCommandError.

        `unsigned` reads the result as a 32-bit value instead (ticks and bank levels use all 32 bits). A pigpiod
        that does not answer in time raises TimeoutError (an OSError, like a reset connection).
        """
        answer = await self._exchange(cmd, p1, p2, extension)
        if unsigned:
            return answer.result & 0xFFFFFFFF
        if answer.result < 0:
            raise PigpioCommandError(cmd, p1, p2, answer.result)
        return answer.result

    async def query(self, cmd: int, p1: int = 0, p2: int = 0) -> bytes:
        """Send a command whose answer carries data (PROCP) and return the data; errors as `command`."""
        answer = await self._exchange(cmd, p1, p2, b"")
        if answer.result < 0:
            raise PigpioCommandError(cmd, p1, p2, answer.result)
        return answer.data

    async def _exchange(self, cmd: int, p1: int, p2: int, extension: bytes) -> Answer:
        async with self._lock:
            self._writer.write(encode_command(cmd, p1, p2, extension))
            async with asyncio.timeout(self.timeout_s):
                return await self.read_answer()

    def post(self, cmd: int, p1: int = 0, p2: int = 0, extension: bytes = b"") -> None:
        """Send a command without waiting for its answer (never blocks: the socket buffers it)."""
        self._writer.write(encode_command(cmd, p1, p2, extension))

    def hold_answers(self) -> None:
        """Leave pigpiod's answers in the kernel until `release_answers`: answers owed to commands sent without
        waiting then wake nobody as they arrive (the event loop stops watching the socket meanwhile)."""
        self._read_transport().pause_reading()

    def release_answers(self) -> None:
        """Read answers again as they arrive (those held come at once)."""
        self._read_transport().resume_reading()

    def _read_transport(self) -> asyncio.ReadTransport:
        transport = self._writer.transport
        assert isinstance(transport, asyncio.ReadTransport)
        return transport

    async def read_answer(self) -> Answer:
        """The next answer on the socket, with its data; a closed socket raises ConnectionResetError."""
        try:
            header = await self._reader.readexactly(COMMAND.size)
            cmd = int(COMMAND.unpack(header)[0])
            result = decode_result(header)
            data = await self._reader.readexactly(result) if cmd in EXTENDED_ANSWERS and result > 0 else b""
        except asyncio.IncompleteReadError as error:
            raise ConnectionResetError("pigpiod closed the command socket") from error
        return Answer(cmd, result, data)

    def is_closing(self) -> bool:
        """Whether the socket is closed or being closed."""
        return self._writer.is_closing()

    def abort(self) -> None:
        """Close the socket now, dropping anything not yet sent (no wait)."""
        self._writer.transport.abort()

    async def close(self) -> None:
        """Close the socket."""
        self._writer.close()
        with contextlib.suppress(OSError):  # already reset by the other end: closed all the same
            await self._writer.wait_closed()


async def open_notifications(
    host: str, port: int, timeout_s: float
) -> tuple[int, asyncio.StreamReader, asyncio.StreamWriter]:
    """Open a socket, turn it into a notification socket with NOIB; returns (handle, reader, writer)."""
    reader, writer = await _open(host, port, timeout_s)
    try:
        writer.write(encode_command(Cmd.NOIB))
        async with asyncio.timeout(timeout_s):
            answer = await reader.readexactly(COMMAND.size)
    except (OSError, TimeoutError, asyncio.IncompleteReadError) as error:
        writer.close()
        raise PigpiodUnavailableError(host, port, f"no answer to NOIB: {error!r}") from error
    handle = decode_result(answer)
    if handle < 0:
        writer.close()
        raise PigpioCommandError(Cmd.NOIB, 0, 0, handle)
    return handle, reader, writer


NOTIFY_RECEIVE_BUFFER = 1 << 20
"""Receive buffer asked for a polled notification socket: reports wait in the kernel between two reads."""


async def open_notification_socket(host: str, port: int, timeout_s: float) -> tuple[int, socket.socket]:
    """A notification socket (NOIB) as a plain non-blocking socket that the event loop does not watch; (handle,
    socket).

    Its owner reads it when it wants the reports (`socket.recv_into` until it would block), so a stream of reports
    wakes nobody: pigpiod flushes them every millisecond, and an asyncio stream would wake the loop for each flush.
    """
    loop = asyncio.get_running_loop()
    try:
        async with asyncio.timeout(timeout_s):
            infos = await loop.getaddrinfo(host, port, type=socket.SOCK_STREAM)
            family, kind, proto, _, address = infos[0]
            sock = socket.socket(family, kind, proto)
            try:
                sock.setblocking(False)
                with contextlib.suppress(OSError):  # the kernel caps it (net.core.rmem_max): a wish, not a need
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, NOTIFY_RECEIVE_BUFFER)
                await loop.sock_connect(sock, address)
                await loop.sock_sendall(sock, encode_command(Cmd.NOIB))
                answer = b""
                while len(answer) < COMMAND.size:
                    chunk = await loop.sock_recv(sock, COMMAND.size - len(answer))
                    if not chunk:
                        raise ConnectionResetError("pigpiod closed the socket before answering NOIB")
                    answer += chunk
            except BaseException:
                sock.close()
                raise
    except (OSError, TimeoutError) as error:
        raise PigpiodUnavailableError(host, port, error or "timed out") from error
    handle = decode_result(answer)
    if handle < 0:
        sock.close()
        raise PigpioCommandError(Cmd.NOIB, 0, 0, handle)
    return handle, sock


def stop_pigpio_client(pi: Any, timeout_s: float = 1.0) -> None:
    """Stop a `pigpio.pi` client once its notification thread has ended (blocking; see end_pigpio_notifications)."""
    end_pigpio_notifications(pi, timeout_s)
    pi.stop()


def end_pigpio_notifications(pi: Any, timeout_s: float = 1.0) -> None:
    """End a `pigpio.pi` client's notification thread and wait for it, up to `timeout_s`; its commands still work."""
    # pigpio's notification thread loops on recv() until its `go` flag drops; `pi.stop()` drops it and sends NC on
    # the thread's socket. If pigpiod closed that socket first, the thread spins on end-of-file, and NC draws a reset
    # that its recv() can raise in that thread; if pigpiod is slow, the thread outlives the client and sees whatever
    # happens to the socket later. So end the thread here: drop the flag, shut the socket's reading side (its recv
    # returns at once, nothing is sent), wait for it; `pi.stop()` then sends no NC. pigpiod frees the handle when
    # the thread closes the socket. `_notify` and `sl` are the pigpio library's private names (it has been at 1.78
    # since 2020).
    notify = getattr(pi, "_notify", None)
    if notify is None:
        return
    notify.go = False
    with contextlib.suppress(OSError, AttributeError):  # already closed, or never opened
        notify.sl.s.shutdown(socket.SHUT_RD)
    if notify.is_alive():
        notify.join(timeout_s)


def probe(host: str, port: int, timeout_s: float) -> None:
    """Check that something accepts connections at host:port, or raise PigpiodUnavailableError (blocking)."""
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            pass
    except OSError as error:
        raise PigpiodUnavailableError(host, port, error) from error


ANSWERS_READ_BYTES = 1 << 16  # a read of the command pipe's answers: far more than a period of motor writes owes


class CommandPipe:
    """Commands to pigpiod sent without waiting for their answers, from plain (not asyncio) code; never blocks.

    For the motors' hot path: each `send` is one write of all its commands to a non-blocking socket, in order (pigpiod
    carries out one socket's commands in order), and returns; the answers are read when they have already arrived
    (at the next `send`, or `collect`), so a refused command is reported one period late, and a pigpiod that stops
    answering is reported once `MAX_OWED` answers are owed, or the kernel will take no more: the caller stops the
    motors some other way. pigpio's own client waits for each answer on the caller's thread: on the event loop, a
    stalled pigpiod would stall everything.
    """

    MAX_OWED = 256
    """Answers owed before pigpiod counts as stalled: about a second of motor writes."""

    def __init__(self, host: str, port: int, timeout_s: float) -> None:
        try:
            self._sock = socket.create_connection((host, port), timeout=timeout_s)  # blocking: call it off the loop
        except OSError as error:
            raise PigpiodUnavailableError(host, port, error) from error
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock.setblocking(False)
        self._unread = bytearray()
        self._owed = 0
        self.broken = False
        """True once a send failed or pigpiod stopped answering: nothing more is sent."""

    @property
    def owed(self) -> int:
        """Answers not yet read."""
        return self._owed

    def send(self, commands: Sequence[tuple[int, int, int]]) -> None:
        """Send (cmd, p1, p2) commands in one write, without waiting; raise PigpioCommandError for an earlier command
        pigpiod refused and ConnectionError when pigpiod is gone or stalled."""
        self.collect()
        if self.broken:
            raise ConnectionError("the command pipe to pigpiod is broken")
        if self._owed > self.MAX_OWED:
            self.broken = True
            raise ConnectionError(f"pigpiod has not answered {self._owed} commands: stalled")
        data = b"".join(encode_command(cmd, p1, p2) for cmd, p1, p2 in commands)
        try:
            sent = self._sock.send(data)
        except BlockingIOError:
            sent = 0
        except OSError:
            self.broken = True
            raise
        if sent < len(data):  # a partial command would garble every one after it
            self.broken = True
            raise ConnectionError("pigpiod takes no more commands: stalled")
        self._owed += len(commands)

    def collect(self) -> None:
        """Read the answers that have arrived (never waits); raise PigpioCommandError for a refused command."""
        while True:
            try:
                data = self._sock.recv(ANSWERS_READ_BYTES)
            except BlockingIOError:
                break
            except OSError:
                self.broken = True
                raise
            if not data:
                self.broken = True
                raise ConnectionResetError("pigpiod closed the command pipe")
            self._unread += data
            if len(data) < ANSWERS_READ_BYTES:  # that was all: no second call only to hear it would block
                break
        whole = len(self._unread) - len(self._unread) % COMMAND.size
        if not whole:
            return
        answers, self._unread = bytes(self._unread[:whole]), self._unread[whole:]
        self._owed -= whole // COMMAND.size
        for cmd, p1, p2, word in COMMAND.iter_unpack(answers):
            if (result := signed_result(word)) < 0:  # pigpiod refused the command
                raise PigpioCommandError(cmd, p1, p2, result)

    def flush(self, timeout_s: float) -> bool:
        """Wait (blocking, at most `timeout_s`) until every command sent has been answered; whether it was. For an
        orderly close only: a broken pipe returns at once."""
        deadline = time.monotonic() + timeout_s
        while self._owed > 0 and not self.broken:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not select.select([self._sock], [], [], remaining)[0]:
                return False
            with contextlib.suppress(PigpioCommandError):  # closing: a refusal changes nothing any more
                self.collect()
        return self._owed <= 0

    def close(self) -> None:
        """Close the socket (answers not read are dropped)."""
        self.broken = True
        self._sock.close()
