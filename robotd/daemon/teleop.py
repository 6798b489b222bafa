"""UDP teleop: fixed-layout, versioned, HMAC-SHA256-authenticated datagrams carrying a body-frame twist.

Theory of operation. Every datagram is exactly `DATAGRAM_SIZE` bytes, big-endian (see `LAYOUT`): magic, version,
type, a random per-run sender session id, a sequence number, the daemon's instance nonce, the sender's Unix time,
vx, vy, wz as float64, and an HMAC-SHA256 tag over everything before it (all zeros when unauthenticated). The
receiver is sans-I/O: `TeleopReceiver.datagram(bytes, now, wall_time, source)` returns a command, a stop, an answer
to send back, or None after counting why it dropped the datagram. Checks run cheapest first: the per-source rate
limit before anything is parsed, the HMAC after the shape, and no state moves until the datagram is authenticated,
so forged traffic cannot move the replay window or the clock estimate.

Instances. Each receiver draws a random `instance` nonce when it is built, i.e. once per daemon start. A client
asks for it with a HELLO and the daemon answers with a WELCOME carrying it; the client echoes it in every command,
and a command for another instance (a capture replayed after a restart, or a client that has not noticed the
restart) is refused as `stale_session` and answered with a WELCOME too, so a live client re-synchronises within one
round trip. A WELCOME is the size of the request it answers (never an amplifier), at most `ANSWERS_PER_S` a second
go to one source, and its tag covers the request's tag, so a client takes only an answer to a datagram it sent
recently. A hello is answered whatever the sender's clock: the welcome carries ours, so a client can say that its
clock is off. Unauthenticated, anyone may ask for the nonce: it then only stops blind replays of recordings.

Time. The sender stamps Unix time because it is the only clock two machines can share; monotonic clocks have
unrelated origins. Two checks use it: (1) when the receiver knows its own Unix time, a sender clock more than
`max_clock_offset_s` away is refused; (2) per session the receiver tracks the smallest (arrival - sender time)
seen, i.e. the clock offset plus the best network delay, and drops datagrams delayed `max_age_s` beyond it: a Wi-Fi
burst of queued commands is stale. The estimate may creep up by `CLOCK_DRIFT` (s/s) so a sender clock slewed by
NTP is followed, not locked out.

Order. Only a sequence number above the session's highest is accepted (an old command must never overwrite a
newer one); a 64-wide window of seen numbers tells replays from late arrivals for the counters. One session
drives at a time: another session takes over only after the current one has been silent `takeover_s`, and only
with sender times later than any accepted before (an older session's datagrams are replays).
"""

from __future__ import annotations

import enum
import hmac
import logging
import math
import secrets
import stat
import struct
from collections import Counter, OrderedDict
from collections.abc import Hashable
from dataclasses import dataclass
from pathlib import Path

from robotd.config.model import TeleopConfig
from robotd.config.schema import ConfigError
from robotd.config.smallfile import SmallFileError, read_small_file, regular_file
from robotd.daemon.ratelimit import SourceRateLimiter
from robotd.kinematics import Twist

log = logging.getLogger(__name__)

MAGIC = b"RBT"
VERSION = 2
INSTANCE_SIZE = 16
# magic, version, type, reserved, session, sequence, instance, time, vx, vy, wz
_HEADER = struct.Struct(f">3sBB3xII{INSTANCE_SIZE}sdddd")
HEADER_SIZE = _HEADER.size
TAG_SIZE = 32
DATAGRAM_SIZE = HEADER_SIZE + TAG_SIZE
_NO_TAG = bytes(TAG_SIZE)
NO_INSTANCE = bytes(INSTANCE_SIZE)
MIN_KEY_BYTES = 16
MAX_KEY_FILE_BYTES = 4096  # a key is 16 to a few hundred bytes; a bigger file is the wrong file
WINDOW = 64  # sequence numbers remembered below the highest, to tell replays from late arrivals
CLOCK_DRIFT = 1e-3  # s/s the per-session clock offset estimate may rise (1000 ppm covers any NTP slew)
ANSWERS_PER_S = 5.0  # WELCOMEs a second to one source (a burst of as many): a client needs one per daemon start
BURST_S = 0.25  # a source's bucket holds this many seconds of its rate: a client's key-press bursts pass
_SESSION = struct.Struct(">II")  # session and sequence, at offset 8
_TIME = struct.Struct(">d")
_INSTANCE = slice(16, 16 + INSTANCE_SIZE)
_TWIST = slice(16 + INSTANCE_SIZE + 8, HEADER_SIZE)

LAYOUT = (
    # offset, size, field, meaning
    (0, 3, "magic", 'b"RBT"'),
    (3, 1, "version", "2"),
    (4, 1, "type", "1 = command, 2 = stop, 3 = hello (client asks), 4 = welcome (daemon answers)"),
    (5, 3, "reserved", "zero"),
    (8, 4, "session", "u32, random and non-zero per sender run (a welcome: the request's)"),
    (12, 4, "sequence", "u32, +1 for each datagram of a session, from 1 (a welcome: the request's)"),
    (16, 16, "instance", "the daemon's nonce for this start (a hello: zero)"),
    (32, 8, "sender_time", "f64, sender's Unix time in seconds (a welcome: the daemon's)"),
    (40, 8, "vx", "f64, m/s forward (zero in a stop, hello or welcome)"),
    (48, 8, "vy", "f64, m/s left"),
    (56, 8, "wz", "f64, rad/s counter-clockwise"),
    (64, 32, "tag", "HMAC-SHA256(key, bytes 0..63), a welcome's over bytes 0..63 + the request's tag; zero unkeyed"),
)


class MessageType(enum.IntEnum):
    """The `type` byte."""

    COMMAND = 1
    STOP = 2
    HELLO = 3
    WELCOME = 4


_REQUESTS = frozenset((MessageType.COMMAND, MessageType.STOP, MessageType.HELLO))  # what a daemon takes


class Reject(enum.Enum):
    """Why a datagram was dropped; each has a counter."""

    RATE_LIMITED = "rate_limited"  # its source sent more than max_datagrams_per_s (or asked for too many answers)
    OVERSIZED = "oversized"  # longer than DATAGRAM_SIZE
    MALFORMED = "malformed"  # short, bad magic, reserved bits or type
    VERSION = "version"  # a wire format version we do not speak
    UNAUTHENTICATED = "unauthenticated"  # zero tag while a key is required
    BAD_TAG = "bad_tag"  # tag does not verify
    NON_FINITE = "non_finite"  # NaN or infinite time or velocity
    CLOCK_OFFSET = "clock_offset"  # sender clock too far from ours
    STALE_SESSION = "stale_session"  # for another daemon instance (answered with this one's)
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


@dataclass(frozen=True, slots=True)
class Answer:
    """A datagram to send back to the source of the request (a WELCOME), no larger than the request."""

    datagram: bytes


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
    return hmac.digest(key, header, "sha256")  # the one-shot form: a fraction of hmac.new()'s cost per datagram


class TeleopSender:
    """Builds datagrams for one sender session and takes the daemon's answers (sans-I/O: no clock, no socket)."""

    def __init__(self, key: bytes | None, session: int | None = None, instance: bytes | None = None) -> None:
        if key is not None and len(key) < MIN_KEY_BYTES:
            raise ValueError(f"a teleop key needs at least {MIN_KEY_BYTES} bytes")
        if instance is not None and (len(instance) != INSTANCE_SIZE or instance == NO_INSTANCE):
            raise ValueError(f"a daemon instance is {INSTANCE_SIZE} bytes, not all zero")
        self.key = key
        self.session = session if session is not None else secrets.randbits(32) | 1
        self.sequence = 0
        self.instance = instance  # the daemon's nonce, None until a welcome brought it
        self.daemon_time = math.nan  # the daemon's Unix time in the latest welcome (0 when it did not know it)
        self._sent: OrderedDict[int, bytes] = OrderedDict()  # sequence -> tag of the latest datagrams, for answers

    def hello(self, sender_time: float) -> bytes:
        """A request for the daemon's instance nonce."""
        return self._encode(MessageType.HELLO, NO_INSTANCE, Twist(0.0, 0.0, 0.0), sender_time)

    def command(self, twist: Twist, sender_time: float) -> bytes:
        """A command datagram for `twist`, stamped with the sender's Unix time (zero instance before a welcome)."""
        return self._encode(MessageType.COMMAND, self.instance or NO_INSTANCE, twist, sender_time)

    def stop(self, sender_time: float) -> bytes:
        """An explicit stop datagram."""
        return self._encode(MessageType.STOP, self.instance or NO_INSTANCE, Twist(0.0, 0.0, 0.0), sender_time)

    def take_answer(self, data: bytes) -> bool:
        """Adopt the instance of a genuine welcome to one of our latest datagrams; True when it changed ours."""
        if len(data) != DATAGRAM_SIZE or data[:3] != MAGIC or data[3] != VERSION or data[4] != MessageType.WELCOME:
            return False
        header, tag = data[:HEADER_SIZE], data[HEADER_SIZE:]
        session, sequence = _SESSION.unpack_from(header, 8)
        instance = bytes(header[_INSTANCE])
        request_tag = self._sent.get(sequence)
        if session != self.session or request_tag is None or instance == NO_INSTANCE:
            return False
        expected = _tag(self.key, header + request_tag) if self.key is not None else _NO_TAG
        if not hmac.compare_digest(tag, expected):
            return False
        # an answer is good once: an older one replayed later must not roll the instance back
        self._sent.clear()
        changed = instance != self.instance
        self.instance = instance
        self.daemon_time = _TIME.unpack_from(header, 16 + INSTANCE_SIZE)[0]
        return changed

    def _encode(self, kind: MessageType, instance: bytes, twist: Twist, sender_time: float) -> bytes:
        self.sequence = (self.sequence + 1) & 0xFFFFFFFF
        header = _HEADER.pack(
            MAGIC, VERSION, kind, self.session, self.sequence, instance, sender_time, twist.vx, twist.vy, twist.wz
        )
        tag = _tag(self.key, header) if self.key is not None else _NO_TAG
        self._sent[self.sequence] = tag
        if len(self._sent) > WINDOW:
            self._sent.popitem(last=False)
        return header + tag


@dataclass(slots=True)
class _Session:
    """What the receiver remembers of the sender session that is driving."""

    session: int
    highest: int  # highest accepted sequence number
    seen: int  # bit i set: sequence (highest - 1 - i) was accepted
    offset: float  # smallest (arrival - sender time) seen: clock offset plus best delay
    last_arrival: float
    last_sender_time: float


@dataclass(frozen=True, slots=True)
class _AnswerDue:
    """An authenticated hello, or a command for another instance: both get a welcome."""

    session: int
    sequence: int
    request_tag: bytes
    stale: bool  # a command for another instance (counted), not a hello


class TeleopReceiver:
    """Validates teleop datagrams (sans-I/O): bytes, arrival time and source in; a message, an answer or None out."""

    def __init__(
        self,
        key: bytes | None,
        *,
        allow_unauthenticated: bool = False,
        max_age_s: float = 0.25,
        max_clock_offset_s: float = 5.0,
        takeover_s: float = 0.5,
        limiter: SourceRateLimiter | None = None,
        instance: bytes | None = None,
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
        self.limiter = limiter
        self.instance = instance if instance is not None else secrets.token_bytes(INSTANCE_SIZE)
        if len(self.instance) != INSTANCE_SIZE or self.instance == NO_INSTANCE:
            raise ValueError(f"a daemon instance is {INSTANCE_SIZE} bytes, not all zero")
        max_sources = limiter.max_sources if limiter is not None else 256
        self.answer_limiter = SourceRateLimiter(ANSWERS_PER_S, ANSWERS_PER_S, max_sources)
        self.rejected: Counter[Reject] = Counter()
        self.accepted = 0
        self.answered = 0
        self.read_pauses = 0  # counted by the socket: times a flood spent the read budget and reading paused
        self._session: _Session | None = None
        self._latest_sender_time = -math.inf  # over every session accepted so far

    @classmethod
    def from_config(cls, config: TeleopConfig, key: bytes | None) -> TeleopReceiver:
        """A receiver with the limits of the configuration (and a fresh instance nonce)."""
        rate = config.max_datagrams_per_s
        return cls(
            key,
            allow_unauthenticated=config.allow_unauthenticated,
            max_age_s=config.max_datagram_age_s,
            max_clock_offset_s=config.max_clock_offset_s,
            takeover_s=config.deadman_timeout_s,
            limiter=SourceRateLimiter(rate, max(1.0, rate * BURST_S), config.max_sources),
        )

    def counters(self) -> dict[str, int]:
        """Accepted, answered and rejected datagrams, by reason (every reason present, zero or not)."""
        counts = {"accepted": self.accepted, "answered": self.answered, "read_pauses": self.read_pauses}
        return counts | {reason.value: self.rejected[reason] for reason in Reject}

    def datagram(
        self, data: bytes, now: float, wall_time: float | None = None, source: Hashable | None = None
    ) -> TeleopMessage | Answer | None:
        """Check one datagram from `source` that arrived at monotonic `now` (and Unix time `wall_time`, if known)."""
        if source is not None and self.limiter is not None and not self.limiter.admit(source, now):
            self.rejected[Reject.RATE_LIMITED] += 1  # first, before anything is parsed: a flood costs little
            return None
        outcome = self._check(data, now, wall_time)
        if isinstance(outcome, Reject):
            self.rejected[outcome] += 1
            return None
        if isinstance(outcome, _AnswerDue):
            return self._welcome(outcome, now, wall_time, source)
        self.accepted += 1
        return outcome

    def _welcome(self, due: _AnswerDue, now: float, wall_time: float | None, source: Hashable | None) -> Answer | None:
        if due.stale:
            self.rejected[Reject.STALE_SESSION] += 1
        if source is not None and not self.answer_limiter.admit(source, now):
            if not due.stale:
                self.rejected[Reject.RATE_LIMITED] += 1
            return None
        self.answered += 1
        header = _HEADER.pack(
            MAGIC, VERSION, MessageType.WELCOME, due.session, due.sequence, self.instance,
            wall_time if wall_time is not None else 0.0, 0.0, 0.0, 0.0,
        )  # fmt: skip
        tag = _tag(self.key, header + due.request_tag) if self.key is not None else _NO_TAG
        return Answer(header + tag)

    def _check(self, data: bytes, now: float, wall_time: float | None) -> TeleopMessage | _AnswerDue | Reject:
        if len(data) > DATAGRAM_SIZE:
            return Reject.OVERSIZED
        if len(data) < DATAGRAM_SIZE or data[:3] != MAGIC:
            return Reject.MALFORMED
        if data[3] != VERSION:
            return Reject.VERSION
        header, tag = data[:HEADER_SIZE], data[HEADER_SIZE:]
        _magic, _version, kind, session, sequence, instance, sender_time, vx, vy, wz = _HEADER.unpack(header)
        if kind not in _REQUESTS or header[5:8] != b"\0\0\0" or session == 0:
            return Reject.MALFORMED
        if kind == MessageType.HELLO and (instance != NO_INSTANCE or any(header[_TWIST])):
            return Reject.MALFORMED
        if tag == _NO_TAG:
            if not self.allow_unauthenticated:
                return Reject.UNAUTHENTICATED
        elif self.key is None or not hmac.compare_digest(tag, _tag(self.key, header)):
            return Reject.BAD_TAG
        if not all(map(math.isfinite, (sender_time, vx, vy, wz))):
            return Reject.NON_FINITE
        if kind == MessageType.HELLO:  # whatever its clock: the welcome carries ours, so a client can tell it is off
            return _AnswerDue(session, sequence, tag, stale=False)
        offset_limit = self.max_clock_offset_s
        if wall_time is not None and offset_limit > 0.0 and abs(wall_time - sender_time) > offset_limit:
            return Reject.CLOCK_OFFSET
        if instance != self.instance:
            return _AnswerDue(session, sequence, tag, stale=True)
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
