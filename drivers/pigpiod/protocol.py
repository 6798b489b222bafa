"""pigpio's socket protocol as data: command numbers, error codes, the command framing and the report layout.

Sans-I/O: `CommandDecoder.feed(bytes)` returns whole commands and never touches a socket.

Theory of operation (facts from pigpio's socket interface documentation and its Python client):
- A command is 16 bytes, four little-endian uint32: cmd, p1, p2, p3. When p3 is not zero, p3 more bytes follow
  (the "extension", e.g. the duty cycle of a hardware PWM command).
- The answer is 16 bytes: cmd, p1, p2 echoed, then the result as a uint32 holding a signed int (< 0 is an error).
- Answers that carry data (PROCP's script status) say how many bytes follow in the result; they follow at once.
- A socket that sends NOIB (99) becomes a notification socket: after the answer (the handle), pigpiod writes 12-byte
  reports `<HHII` seq, flags, tick, level on it. seq counts reports per handle (16 bits, wrapping); flags 0 means a
  level change (level = all of bank 1, GPIO 0-31, after the change, tick = its time in microseconds, 32 bits).
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

COMMAND = struct.Struct("<IIII")
"""A command and its answer: cmd, p1, p2, p3 (the answer's last word is the result)."""

REPORT_SIZE = 12
REPORT_DTYPE = np.dtype([("seq", "<u2"), ("flags", "<u2"), ("tick", "<u4"), ("level", "<u4")])
"""One notification report, as numpy reads and writes it in bulk."""

MAX_EXTENSION = 1 << 16
"""Largest extension accepted; a bigger p3 is a corrupt stream (pigpio's own commands send at most a few KiB)."""


class Cmd(enum.IntEnum):
    """pigpio command numbers (the subset robotd and gpiozero's PiGPIOFactory use, plus their neighbours)."""

    MODES = 0
    MODEG = 1
    PUD = 2
    READ = 3
    WRITE = 4
    PWM = 5
    PRS = 6
    PFS = 7
    SERVO = 8
    WDOG = 9
    BR1 = 10
    BR2 = 11
    BC1 = 12
    BC2 = 13
    BS1 = 14
    BS2 = 15
    TICK = 16
    HWVER = 17
    NO = 18
    NB = 19
    NP = 20
    NC = 21
    PRG = 22
    PFG = 23
    PRRG = 24
    PIGPV = 26
    PROC = 38
    PROCD = 39
    PROCR = 40
    PROCS = 41
    PROCP = 45
    MICS = 46
    MILS = 47
    GDC = 83
    GPW = 84
    FG = 97
    FN = 98
    NOIB = 99
    PROCU = 117  # pigpio numbered it after the others: 52 is WVTXR


class Err(enum.IntEnum):
    """pigpio error codes returned as negative results."""

    BAD_USER_GPIO = -2
    BAD_GPIO = -3
    BAD_MODE = -4
    BAD_LEVEL = -5
    BAD_PUD = -6
    BAD_DUTYCYCLE = -8
    BAD_DUTYRANGE = -21
    NO_HANDLE = -24
    BAD_HANDLE = -25
    NOT_PERMITTED = -41
    BAD_SCRIPT = -47
    BAD_SCRIPT_ID = -48
    DUP_TAG = -53
    TOO_MANY_TAGS = -54
    BAD_SCRIPT_CMD = -55
    NO_SCRIPT_ROOM = -57
    TOO_MANY_PARAM = -61
    NOT_HALTED = -62
    BAD_TAG = -63
    BAD_MICS_DELAY = -64
    BAD_MILS_DELAY = -65
    UNKNOWN_COMMAND = -88
    NOT_PWM_GPIO = -92
    BAD_FILTER = -125


class Mode(enum.IntEnum):
    """GPIO modes as pigpio numbers them (ALT functions are not in numeric order)."""

    INPUT = 0
    OUTPUT = 1
    ALT5 = 2
    ALT4 = 3
    ALT0 = 4
    ALT1 = 5
    ALT2 = 6
    ALT3 = 7


class Pull(enum.IntEnum):
    """Pull-up/down resistor settings."""

    OFF = 0
    DOWN = 1
    UP = 2


class ScriptState(enum.IntEnum):
    """Run status of a stored script, as PROCP answers it."""

    INITING = 0
    HALTED = 1
    RUNNING = 2
    WAITING = 3
    FAILED = 4


MAX_SCRIPTS = 32
MAX_SCRIPT_PARAMS = 10
SCRIPT_STATUS = struct.Struct("<11i")
"""PROCP's data: the run status, then parameters p0..p9 (signed 32-bit)."""
EXTENDED_ANSWERS = frozenset({Cmd.PROCP})
"""Commands whose answer is followed by as many data bytes as its (non-negative) result says."""

NTFY_FLAGS_EVENT = 1 << 7
NTFY_FLAGS_ALIVE = 1 << 6
NTFY_FLAGS_WDOG = 1 << 5
NTFY_FLAGS_GPIO = 31


@dataclass(frozen=True, slots=True)
class Command:
    """One command read from a socket."""

    cmd: int
    p1: int
    p2: int
    p3: int
    extension: bytes = b""


class ProtocolError(Exception):
    """A stream that cannot be pigpio commands (the connection should be closed)."""


class CommandDecoder:
    """Cuts a byte stream into commands; keeps partial commands between calls."""

    def __init__(self) -> None:
        self._buffer = bytearray()

    def feed(self, data: bytes) -> list[Command]:
        """Add received bytes; return every command now complete, in order."""
        self._buffer += data
        commands: list[Command] = []
        offset = 0
        while len(self._buffer) - offset >= COMMAND.size:
            cmd, p1, p2, p3 = COMMAND.unpack_from(self._buffer, offset)
            if p3 > MAX_EXTENSION:
                raise ProtocolError(f"command {cmd} announces {p3} extension bytes (at most {MAX_EXTENSION})")
            end = offset + COMMAND.size + p3
            if len(self._buffer) < end:
                break
            commands.append(Command(cmd, p1, p2, p3, bytes(self._buffer[offset + COMMAND.size : end])))
            offset = end
        del self._buffer[:offset]
        return commands


def encode_answer(command: Command, result: int) -> bytes:
    """The 16-byte answer to a command: its first three words echoed, then the result as a signed 32-bit value."""
    return COMMAND.pack(command.cmd, command.p1, command.p2, result & 0xFFFFFFFF)


def encode_command(cmd: int, p1: int = 0, p2: int = 0, extension: bytes = b"") -> bytes:
    """A command as a client sends it."""
    return COMMAND.pack(cmd, p1 & 0xFFFFFFFF, p2 & 0xFFFFFFFF, len(extension)) + extension


def encode_params(params: tuple[int, ...] | list[int]) -> bytes:
    """Script parameters as PROCR and PROCU send them: one 32-bit word each (negative values wrap)."""
    return struct.pack(f"<{len(params)}I", *(value & 0xFFFFFFFF for value in params))


def decode_params(extension: bytes) -> tuple[int, ...]:
    """Script parameters from a PROCR or PROCU extension, as the signed values a script sees."""
    return struct.unpack(f"<{len(extension) // 4}i", extension[: len(extension) // 4 * 4])


def decode_result(answer: bytes) -> int:
    """The signed result of a 16-byte answer."""
    return signed_result(int(COMMAND.unpack(answer)[3]))


def signed_result(word: int) -> int:
    """An answer's result field (unsigned 32-bit, as COMMAND unpacks it) as the signed value pigpiod meant."""
    return word - (1 << 32) if word & 0x80000000 else word


def encode_reports(
    seq: npt.NDArray[np.uint16], ticks: npt.NDArray[np.uint32], levels: npt.NDArray[np.uint32], flags: int = 0
) -> bytes:
    """Many reports as one `bytes`, built in bulk."""
    reports = np.empty(len(ticks), dtype=REPORT_DTYPE)
    reports["seq"] = seq
    reports["flags"] = flags
    reports["tick"] = ticks
    reports["level"] = levels
    return reports.tobytes()


def decode_reports(data: bytes | bytearray | memoryview) -> npt.NDArray[np.void]:
    """Whole reports of a buffer as a structured array (a trailing partial report must be cut off by the caller)."""
    return np.frombuffer(data, dtype=REPORT_DTYPE, count=len(data) // REPORT_SIZE)
