"""UDP teleop: a fixed-layout, versioned, HMAC-SHA256-authenticated datagram carrying a body-frame twist.

Theory of operation. Every datagram is exactly `DATAGRAM_SIZE` bytes, big-endian (see `LAYOUT`): magic, version,
type (command or stop), a random per-run sender session id, a sequence number, the sender's Unix time, vx, vy, wz
as float64, and an HMAC-SHA256 tag over everything before it (all zeros when unauthenticated). The receiver is
sans-I/O: `TeleopReceiver.datagram(bytes, now)` returns a command, a stop, or None after counting why it dropped it.
Checks run cheapest first and never touch state until the datagram is authenticated, so forged traffic cannot move
the replay window or the clock estimate.

Time. The sender stamps Unix time because it is the only clock two machines can share; monotonic clocks have
unrelated origins. Two checks use it: (1) when the receiver knows its own Unix time, a sender clock more than
`max_clock_offset_s` away is refused, which stops a recording from being replayed to a freshly restarted daemon;
(2) per session the receiver tracks the smallest (arrival - sender time) seen, i.e. the clock offset plus the best
network delay, and drops datagrams delayed `max_age_s` beyond it: a Wi-Fi burst of queued commands is stale.
The estimate may creep up by `CLOCK_DRIFT` (s/s) so a sender clock slewed by NTP is followed, not locked out.

Order. Only a sequence number above the session's highest is accepted (an old command must never overwrite a
newer one); a 64-wide window of seen numbers tells replays from late arrivals for the counters. One session
drives at a time: another session takes over only after the current one has been silent `takeover_s`, and only
with sender times later than any accepted before (an older session's datagrams are replays).
"""

from __future__ import annotations

import asyncio
import enum
import hmac
import logging
import math
import secrets
import stat
import struct
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from hashlib import sha256
from pathlib import Path

from robotd.config import TeleopConfig
from robotd.kinematics import Twist
from robotd.schema import ConfigError
from robotd.smallfile import SmallFileError, read_small_file, regular_file

log = logging.getLogger(__name__)

MAGIC = b"RBT"
VERSION = 1
_HEADER = struct.Struct(">3sBB3xIIdddd")  # magic, version, type, reserved, session, sequence, time, vx, vy, wz
TAG_SIZE = 32
DATAGRAM_SIZE = _HEADER.size + TAG_SIZE
_NO_TAG = bytes(TAG_SIZE)
MIN_KEY_BYTES = 16
MAX_KEY_FILE_BYTES = 4096  # a key is 16 to a few hundred bytes; a bigger file is the wrong file
WINDOW = 64  # sequence numbers remembered below the highest, to tell replays from late arrivals
CLOCK_DRIFT = 1e-3  # s/s the per-session clock offset estimate may rise (1000 ppm covers any NTP slew)

LAYOUT = (
    # offset, size, field, meaning
    (0, 3, "magic", 'b"RBT"'),
    (3, 1, "version", "1"),
    (4, 1, "type", "1 = command, 2 = stop"),
    (5, 3, "reserved", "zero"),
    (8, 4, "session", "u32, random and non-zero per sender run"),
    (12, 4, "sequence", "u32, 1 for the first datagram of a session, +1 for each next"),
    (16, 8, "sender_time", "f64, sender's Unix time in seconds"),
    (24, 8, "vx", "f64, m/s forward (zero in a stop)"),
    (32, 8, "vy", "f64, m/s left"),
    (40, 8, "wz", "f64, rad/s counter-clockwise"),
    (48, 32, "tag", "HMAC-SHA256(key, bytes 0..47); 32 zero bytes when unauthenticated"),
)


class MessageType(enum.IntEnum):
    """The `type` byte."""

    COMMAND = 1
    STOP = 2


_TYPES = frozenset(MessageType)


class Reject(enum.Enum):
    """Why a datagram was dropped; each has a counter."""

    OVERSIZED = "oversized"  # longer than DATAGRAM_SIZE
    MALFORMED = "malformed"  # short, bad magic, reserved bits or type
    VERSION = "version"  # a wire format version we do not speak
    UNAUTHENTICATED = "unauthenticated"  # zero tag while a key is required
    BAD_TAG = "bad_tag"  # tag does not verify
    NON_FINITE = "non_finite"  # NaN or infinite time or velocity
    CLOCK_OFFSET = "clock_offset"  # sender clock too far from ours
    STALE = "stale"  # delayed beyond max_age_s
    REPLAYED = "replayed"  # sequence already seen, or from an older session
    OUT_OF_ORDER = "out_of_order"  # older than the newest accepted, not seen before
    BUSY = "busy"  # another sender session is driving


@dataclass(frozen=True, slots=True)
class TeleopCommand:
    """A valid command: drive at `twist`; `received_at` is the receiver's monotonic arrival time."""

    twist: Twist
    session: int
    sequence: int
    received_at: float


@dataclass(frozen=True, slots=True)
class StopCommand:
    """A valid, explicit stop."""

    session: int
    sequence: int
    received_at: float


TeleopMessage = TeleopCommand | StopCommand


def load_key(path: str | Path) -> bytes:
    """The shared key from a key file (surrounding whitespace removed), or ConfigError; never blocks (FIFO, device)."""
    try:
        key = read_small_file(path, MAX_KEY_FILE_BYTES).strip()
    except SmallFileError as error:
        raise ConfigError([f"teleop.key_file: cannot read {path}: {error}"]) from None
    if len(key) < MIN_KEY_BYTES:
        raise ConfigError([f"teleop.key_file: {path} holds {len(key)} bytes; a key needs at least {MIN_KEY_BYTES}"])
    return key


def check_key_file(path: str | Path) -> list[str]:
    """Problems of the daemon's key file: unreadable, not a regular file, a bad key, or readable by other users.

    As for PostgreSQL's key files: a key owned by root may be shared with the daemon's group (0640), any other
    owner must keep it to itself (0600); nobody else may read or write it.
    """
    try:
        info = regular_file(path)
    except SmallFileError as error:
        return [f"teleop.key_file: cannot read {path}: {error}"]
    allowed = 0o640 if info.st_uid == 0 else 0o600
    mode = stat.S_IMODE(info.st_mode)
    if mode & ~allowed:
        exposed = f"{path} has mode {mode:04o}, so other users can read or change the key"
        return [f"teleop.key_file: {exposed}: run `chmod {allowed:04o} {path}`"]
    try:
        load_key(path)
    except ConfigError as error:
        return error.problems
    return []


def _tag(key: bytes, header: bytes) -> bytes:
    return hmac.new(key, header, sha256).digest()


class TeleopSender:
    """Builds datagrams for one sender session (sans-I/O: the caller supplies the time and sends the bytes)."""

    def __init__(self, key: bytes | None, session: int | None = None) -> None:
        if key is not None and len(key) < MIN_KEY_BYTES:
            raise ValueError(f"a teleop key needs at least {MIN_KEY_BYTES} bytes")
        self.key = key
        self.session = session if session is not None else secrets.randbits(32) | 1
        self.sequence = 0

    def command(self, twist: Twist, sender_time: float) -> bytes:
        """A command datagram for `twist`, stamped with the sender's Unix time."""
        return self._encode(MessageType.COMMAND, twist, sender_time)

    def stop(self, sender_time: float) -> bytes:
        """An explicit stop datagram."""
        return self._encode(MessageType.STOP, Twist(0.0, 0.0, 0.0), sender_time)

    def _encode(self, kind: MessageType, twist: Twist, sender_time: float) -> bytes:
        self.sequence = (self.sequence + 1) & 0xFFFFFFFF
        header = _HEADER.pack(MAGIC, VERSION, kind, self.session, self.sequence, sender_time, *_twist(twist))
        return header + (_tag(self.key, header) if self.key is not None else _NO_TAG)


def _twist(twist: Twist) -> tuple[float, float, float]:
    return (twist.vx, twist.vy, twist.wz)


@dataclass(slots=True)
class _Session:
    """What the receiver remembers of the sender session that is driving."""

    session: int
    highest: int  # highest accepted sequence number
    seen: int  # bit i set: sequence (highest - 1 - i) was accepted
    offset: float  # smallest (arrival - sender time) seen: clock offset plus best delay
    last_arrival: float
    last_sender_time: float


class TeleopReceiver:
    """Validates teleop datagrams (sans-I/O): bytes and arrival time in, a command, a stop, or None out."""

    def __init__(
        self,
        key: bytes | None,
        *,
        allow_unauthenticated: bool = False,
        max_age_s: float = 0.25,
        max_clock_offset_s: float = 5.0,
        takeover_s: float = 0.5,
    ) -> None:
        if key is None and not allow_unauthenticated:
            raise ValueError("a teleop receiver without a key needs allow_unauthenticated=True")
        if key is not None and len(key) < MIN_KEY_BYTES:
            raise ValueError(f"a teleop key needs at least {MIN_KEY_BYTES} bytes")
        self.key = key
        self.allow_unauthenticated = allow_unauthenticated
        self.max_age_s = max_age_s
        self.max_clock_offset_s = max_clock_offset_s
        self.takeover_s = takeover_s
        self.rejected: Counter[Reject] = Counter()
        self.accepted = 0
        self._session: _Session | None = None
        self._latest_sender_time = -math.inf  # over every session accepted so far

    @classmethod
    def from_config(cls, config: TeleopConfig, key: bytes | None) -> TeleopReceiver:
        """A receiver with the limits of the configuration."""
        return cls(
            key,
            allow_unauthenticated=config.allow_unauthenticated,
            max_age_s=config.max_datagram_age_s,
            max_clock_offset_s=config.max_clock_offset_s,
            takeover_s=config.deadman_timeout_s,
        )

    def counters(self) -> dict[str, int]:
        """Accepted and rejected datagrams, by reason (every reason present, zero or not)."""
        return {"accepted": self.accepted} | {reason.value: self.rejected[reason] for reason in Reject}

    def datagram(self, data: bytes, now: float, wall_time: float | None = None) -> TeleopMessage | None:
        """Validate one datagram that arrived at monotonic time `now` (and Unix time `wall_time`, when known)."""
        outcome = self._check(data, now, wall_time)
        if isinstance(outcome, Reject):
            self.rejected[outcome] += 1
            return None
        self.accepted += 1
        return outcome

    def _check(self, data: bytes, now: float, wall_time: float | None) -> TeleopMessage | Reject:
        if len(data) > DATAGRAM_SIZE:
            return Reject.OVERSIZED
        if len(data) < DATAGRAM_SIZE or data[:3] != MAGIC:
            return Reject.MALFORMED
        if data[3] != VERSION:
            return Reject.VERSION
        header, tag = data[: _HEADER.size], data[_HEADER.size :]
        _magic, _version, kind, session, sequence, sender_time, vx, vy, wz = _HEADER.unpack(header)
        if kind not in _TYPES or header[5:8] != b"\0\0\0" or session == 0:
            return Reject.MALFORMED
        if tag == _NO_TAG:
            if not self.allow_unauthenticated:
                return Reject.UNAUTHENTICATED
        elif self.key is None or not hmac.compare_digest(tag, _tag(self.key, header)):
            return Reject.BAD_TAG
        if not all(map(math.isfinite, (sender_time, vx, vy, wz))):
            return Reject.NON_FINITE
        offset_limit = self.max_clock_offset_s
        if wall_time is not None and offset_limit > 0.0 and abs(wall_time - sender_time) > offset_limit:
            return Reject.CLOCK_OFFSET
        state = self._session
        sample = now - sender_time
        if state is None or session != state.session:
            if state is not None and now - state.last_arrival < self.takeover_s:
                return Reject.BUSY
            if sender_time <= self._latest_sender_time:
                return Reject.REPLAYED
            state = _Session(session, sequence, 0, sample, now, sender_time)
        else:
            verdict = _order(state, sequence)
            if verdict is not None:
                return verdict
            offset = min(state.offset + CLOCK_DRIFT * max(now - state.last_arrival, 0.0), sample)
            if sample - offset > self.max_age_s:
                return Reject.STALE
            shift = sequence - state.highest
            seen = ((state.seen << shift) | (1 << (shift - 1))) & ((1 << WINDOW) - 1) if shift <= WINDOW else 0
            state = _Session(session, sequence, seen, offset, now, sender_time)
        self._session = state
        self._latest_sender_time = max(self._latest_sender_time, sender_time)
        if kind == MessageType.STOP:
            return StopCommand(session, sequence, now)
        return TeleopCommand(Twist(vx, vy, wz), session, sequence, now)


def _order(state: _Session, sequence: int) -> Reject | None:
    """None when `sequence` is newer than any accepted in the session, else why not."""
    if sequence > state.highest:
        return None
    behind = state.highest - sequence
    if behind == 0 or (behind <= WINDOW and state.seen >> (behind - 1) & 1):
        return Reject.REPLAYED
    return Reject.OUT_OF_ORDER


def receiver_from_config(config: TeleopConfig) -> TeleopReceiver:
    """The receiver the daemon runs: keyed from the key file, or keyless with a warning when allowed."""
    if config.key_file:
        return TeleopReceiver.from_config(config, load_key(config.key_file))
    if not config.allow_unauthenticated:
        raise ConfigError(["teleop.key_file: required unless teleop.allow_unauthenticated is true"])
    log.warning(
        "teleop runs WITHOUT authentication (teleop.allow_unauthenticated): anyone who can reach %s:%d drives",
        config.bind,
        config.port,
    )
    return TeleopReceiver.from_config(config, None)


class TeleopProtocol(asyncio.DatagramProtocol):
    """asyncio adapter: feeds each datagram to a receiver and hands valid messages to `on_message`."""

    def __init__(
        self,
        receiver: TeleopReceiver,
        on_message: Callable[[TeleopMessage], None],
        clock: Callable[[], float] = time.monotonic,
        wall_clock: Callable[[], float] = time.time,
    ) -> None:
        self.receiver = receiver
        self.on_message = on_message
        self.clock = clock
        self.wall_clock = wall_clock

    def datagram_received(self, data: bytes, addr: tuple[str | object, ...]) -> None:  # noqa: ARG002
        """One datagram: validate, then hand on."""
        message = self.receiver.datagram(data, self.clock(), self.wall_clock())
        if message is not None:
            self.on_message(message)

    def error_received(self, exc: Exception) -> None:
        """ICMP errors (a client went away) are normal on UDP: note them, keep serving."""
        log.debug("teleop socket error: %s", exc)


async def open_teleop(
    config: TeleopConfig, receiver: TeleopReceiver, on_message: Callable[[TeleopMessage], None]
) -> asyncio.DatagramTransport:
    """Listen for teleop datagrams on the configured address; the caller closes the transport."""
    loop = asyncio.get_running_loop()
    transport, _protocol = await loop.create_datagram_endpoint(
        lambda: TeleopProtocol(receiver, on_message), local_addr=(config.bind, config.port)
    )
    return transport
