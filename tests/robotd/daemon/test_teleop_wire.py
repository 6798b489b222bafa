"""The teleop wire format and receiver: authentication, replay window, staleness, sessions, instances, hostile input."""

from __future__ import annotations

import hmac
import random
import struct
from hashlib import sha256
from pathlib import Path

import pytest

from robotd.config.model import TeleopConfig
from robotd.config.schema import ConfigError
from robotd.daemon.teleop import (
    ANSWERS_PER_S,
    DATAGRAM_SIZE,
    HEADER_SIZE,
    LAYOUT,
    WINDOW,
    Answer,
    StopCommand,
    TeleopCommand,
    TeleopReceiver,
    TeleopSender,
    load_key,
    receiver_from_config,
)
from robotd.kinematics import Twist

KEY = b"0123456789abcdef-robotd-test-key"
WALL = 1_700_000_000.0  # the sender's and receiver's Unix time at the start of each test
MONO = 500.0  # the receiver's monotonic time at the start


def rejected(receiver: TeleopReceiver) -> dict[str, int]:
    return {
        reason: count
        for reason, count in receiver.counters().items()
        if reason not in ("accepted", "answered", "read_pauses") and count
    }


def synced(key: bytes | None, receiver: TeleopReceiver, session: int | None = None) -> TeleopSender:
    """A sender that already holds the receiver's instance (as after a hello and its welcome)."""
    return TeleopSender(key, session=session, instance=receiver.instance)


def pair(**limits: float) -> tuple[TeleopSender, TeleopReceiver]:
    receiver = TeleopReceiver(KEY, **limits)  # type: ignore[arg-type]
    return synced(KEY, receiver), receiver


def test_a_command_round_trips_with_its_arrival_time() -> None:
    sender, receiver = pair()
    datagram = sender.command(Twist(0.25, -0.5, 1.5), WALL)
    assert len(datagram) == DATAGRAM_SIZE
    message = receiver.datagram(datagram, MONO, WALL + 0.01)
    assert message == TeleopCommand(Twist(0.25, -0.5, 1.5), sender.session, 1, MONO)
    stop = receiver.datagram(sender.stop(WALL + 0.05), MONO + 0.05, WALL + 0.05)
    assert stop == StopCommand(sender.session, 2, MONO + 0.05)
    assert receiver.accepted == 2
    assert rejected(receiver) == {}


def test_the_layout_table_matches_the_encoder() -> None:
    offsets = [offset for offset, *_ in LAYOUT]
    sizes = [size for _, size, *_ in LAYOUT]
    assert [a + b for a, b in zip(offsets, sizes, strict=True)][:-1] == offsets[1:]
    assert offsets[-1] + sizes[-1] == DATAGRAM_SIZE
    instance = bytes(range(1, 17))
    datagram = TeleopSender(KEY, session=0xA1B2C3D4, instance=instance).command(Twist(1.0, 2.0, 3.0), 42.5)
    assert datagram[0:3] == b"RBT"
    assert datagram[3] == 2
    assert datagram[4] == 1
    assert struct.unpack(">II", datagram[8:16]) == (0xA1B2C3D4, 1)
    assert datagram[16:32] == instance
    assert struct.unpack(">dddd", datagram[32:64]) == (42.5, 1.0, 2.0, 3.0)
    assert datagram[64:] == hmac.new(KEY, datagram[:64], sha256).digest()


def test_a_wrong_key_or_a_flipped_bit_fails_authentication() -> None:
    receiver = TeleopReceiver(KEY)
    forged = synced(b"another-key-of-enough-length", receiver).command(Twist(0.1, 0, 0), WALL)
    assert receiver.datagram(forged, MONO, WALL) is None
    genuine = bytearray(synced(KEY, receiver).command(Twist(0.1, 0, 0), WALL))
    genuine[50] ^= 0x01
    assert receiver.datagram(bytes(genuine), MONO, WALL) is None
    assert rejected(receiver) == {"bad_tag": 2}


def test_unauthenticated_datagrams_need_the_explicit_flag() -> None:
    receiver = TeleopReceiver(KEY)
    keyless = synced(None, receiver).command(Twist(0.1, 0, 0), WALL)
    assert receiver.datagram(keyless, MONO, WALL) is None
    assert rejected(receiver) == {"unauthenticated": 1}
    open_receiver = TeleopReceiver(None, allow_unauthenticated=True)
    keyless = synced(None, open_receiver).command(Twist(0.1, 0, 0), WALL)
    assert isinstance(open_receiver.datagram(keyless, MONO, WALL), TeleopCommand)
    with pytest.raises(ValueError, match="allow_unauthenticated"):
        TeleopReceiver(None)


def test_replayed_and_out_of_order_datagrams_are_dropped_and_told_apart() -> None:
    sender, receiver = pair()
    first, second, third = (sender.command(Twist(0.1 * i, 0, 0), WALL + 0.01 * i) for i in range(3))
    assert receiver.datagram(first, MONO, WALL) is not None
    assert receiver.datagram(third, MONO + 0.02, WALL) is not None
    assert receiver.datagram(second, MONO + 0.03, WALL) is None  # late: would undo the newer command
    assert receiver.datagram(third, MONO + 0.04, WALL) is None
    assert receiver.datagram(first, MONO + 0.05, WALL) is None
    assert rejected(receiver) == {"out_of_order": 1, "replayed": 2}


def test_the_replay_window_remembers_the_last_sixty_four() -> None:
    sender, receiver = pair()
    datagrams = [sender.command(Twist(0, 0, 0.1), WALL + i * 1e-3) for i in range(WINDOW + 10)]
    for i, datagram in enumerate(datagrams):
        assert receiver.datagram(datagram, MONO + i * 1e-3, WALL) is not None
    for datagram in datagrams[-WINDOW - 1 :]:
        assert receiver.datagram(datagram, MONO + 1.0, WALL) is None
    assert rejected(receiver) == {"replayed": WINDOW + 1}


def test_a_datagram_delayed_beyond_the_best_path_is_stale() -> None:
    sender, receiver = pair(max_age_s=0.25)
    skew = 3.0  # the sender's clock is 3 s ahead: the offset estimate absorbs it
    for i in range(10):
        sent = WALL + skew + 0.05 * i
        assert receiver.datagram(sender.command(Twist(0.2, 0, 0), sent), MONO + 0.05 * i, WALL + 0.05 * i) is not None
    queued = sender.command(Twist(0.2, 0, 0), WALL + skew + 0.5)
    assert receiver.datagram(queued, MONO + 0.5 + 0.3, WALL + 0.8) is None  # arrived 0.3 s late
    assert rejected(receiver) == {"stale": 1}


def test_a_sender_clock_far_from_ours_is_refused() -> None:
    receiver = TeleopReceiver(KEY, max_clock_offset_s=5.0)
    recorded = synced(KEY, receiver).command(Twist(0.2, 0, 0), WALL - 3600.0)  # a recording from an hour ago
    assert receiver.datagram(recorded, MONO, WALL) is None
    assert rejected(receiver) == {"clock_offset": 1}


def test_one_session_drives_until_it_falls_silent() -> None:
    receiver = TeleopReceiver(KEY, takeover_s=0.5)
    driver, intruder = synced(KEY, receiver), synced(KEY, receiver)
    assert receiver.datagram(driver.command(Twist(0.1, 0, 0), WALL), MONO, WALL) is not None
    assert receiver.datagram(intruder.command(Twist(-0.1, 0, 0), WALL + 0.1), MONO + 0.1, WALL + 0.1) is None
    assert rejected(receiver) == {"busy": 1}
    took_over = receiver.datagram(intruder.command(Twist(-0.1, 0, 0), WALL + 0.7), MONO + 0.7, WALL + 0.7)
    assert isinstance(took_over, TeleopCommand)
    assert took_over.session == intruder.session
    # The old session's datagrams, even fresh ones after the new session falls silent, are older: replays.
    old = driver.command(Twist(0.1, 0, 0), WALL + 0.05)
    assert receiver.datagram(old, MONO + 2.0, WALL + 0.7) is None
    assert rejected(receiver) == {"busy": 1, "replayed": 1}


@pytest.mark.parametrize(
    ("mutate", "reason"),
    [
        (lambda d: d + b"\0", "oversized"),
        (lambda d: d[:-1], "malformed"),
        (lambda d: b"", "malformed"),
        (lambda d: b"XYZ" + d[3:], "malformed"),
        (lambda d: d[:3] + b"\x01" + d[4:], "version"),
    ],
)
def test_wrongly_shaped_datagrams_are_counted_by_reason(mutate: object, reason: str) -> None:
    sender, receiver = pair()
    datagram = sender.command(Twist(0.1, 0, 0), WALL)
    assert callable(mutate)
    assert receiver.datagram(mutate(datagram), MONO, WALL) is None
    assert rejected(receiver) == {reason: 1}


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_velocities_are_rejected(bad: float) -> None:
    sender, receiver = pair()
    assert receiver.datagram(sender.command(Twist(0.1, bad, 0), WALL), MONO, WALL) is None
    assert rejected(receiver) == {"non_finite": 1}


def test_a_bad_type_or_reserved_byte_is_malformed_even_when_signed() -> None:
    for index, value in ((4, 7), (4, 4), (6, 1)):
        receiver = TeleopReceiver(KEY)
        header = bytearray(synced(KEY, receiver).command(Twist(0.1, 0, 0), WALL)[:HEADER_SIZE])
        header[index] = value
        signed = bytes(header) + hmac.new(KEY, bytes(header), sha256).digest()
        assert receiver.datagram(signed, MONO, WALL) is None
        assert rejected(receiver) == {"malformed": 1}


def mutated(rng: random.Random, valid: bytes) -> bytes:
    """A datagram that differs from `valid`: bit flips, byte changes, truncation, extension or random bytes."""
    choice = rng.randrange(6)
    if choice == 0:
        data = bytearray(valid)
        data[rng.randrange(len(data))] ^= 1 << rng.randrange(8)
        return bytes(data)
    if choice == 1:
        data = bytearray(valid)
        index = rng.randrange(len(data))
        data[index] = (data[index] + rng.randrange(1, 256)) % 256
        return bytes(data)
    if choice == 2:
        return valid[: rng.randrange(len(valid))]
    if choice == 3:
        return valid + rng.randbytes(rng.randrange(1, 2000))
    if choice == 4:
        return rng.randbytes(DATAGRAM_SIZE)
    return rng.randbytes(rng.randrange(0, 200))


def fuzz(count: int, seed: int) -> TeleopReceiver:
    rng = random.Random(seed)
    sender, receiver = pair()
    valid = sender.command(Twist(0.3, 0.1, -0.2), WALL)
    assert receiver.datagram(valid, MONO, WALL) is not None  # the receiver holds a live session meanwhile
    receiver.accepted = 0
    for i in range(count):
        assert receiver.datagram(mutated(rng, valid), MONO + i * 1e-5, WALL + i * 1e-5) is None
    return receiver


def test_one_hundred_thousand_hostile_datagrams() -> None:
    """The issue's acceptance figure: 100,000 random and mutated datagrams, none accepted, none crashing."""
    receiver = fuzz(100_000, seed=2024)
    assert receiver.accepted == 0
    assert sum(receiver.rejected.values()) == 100_000
    assert {"oversized", "malformed", "bad_tag"} <= set(rejected(receiver))


def test_key_files(tmp_path: Path) -> None:
    good = tmp_path / "teleop.key"
    good.write_bytes(KEY + b"\n")
    assert load_key(good) == KEY
    short = tmp_path / "short.key"
    short.write_bytes(b"too short\n")
    with pytest.raises(ConfigError, match="at least 16"):
        load_key(short)
    with pytest.raises(ConfigError, match="cannot read"):
        load_key(tmp_path / "missing.key")


def test_running_without_a_key_logs_a_warning(caplog: pytest.LogCaptureFixture) -> None:
    config = TeleopConfig(key_file="", allow_unauthenticated=True)
    receiver = receiver_from_config(config)
    assert receiver.key is None
    assert "WITHOUT authentication" in caplog.text
    with pytest.raises(ConfigError):
        receiver_from_config(TeleopConfig(key_file=""))


# --- daemon instances: hello, welcome, and replays across a restart ------------------------------------------------


def welcome_for(sender: TeleopSender, receiver: TeleopReceiver, request: bytes) -> bytes:
    """The receiver's answer to `request` (which must be one)."""
    answer = receiver.datagram(request, MONO, WALL, source="client")
    assert isinstance(answer, Answer), answer
    return answer.datagram


def test_a_hello_brings_the_instance_in_an_answer_no_larger_than_the_request() -> None:
    receiver, sender = TeleopReceiver(KEY), TeleopSender(KEY)
    hello = sender.hello(WALL)
    answer = welcome_for(sender, receiver, hello)
    assert len(answer) <= len(hello)
    assert receiver.counters()["answered"] == 1
    assert TeleopSender(KEY).instance is None  # a sender has no instance before a welcome
    assert sender.take_answer(answer)
    assert sender.instance == receiver.instance
    assert isinstance(receiver.datagram(sender.command(Twist(0.2, 0, 0), WALL), MONO, WALL), TeleopCommand)
    assert rejected(receiver) == {}


def test_a_capture_replayed_to_a_restarted_daemon_is_refused_as_a_stale_session() -> None:
    """The issue's finding: 20 of 20 captured datagrams drove the motors after a restart, even 11 s old."""
    before_restart = TeleopReceiver(KEY)
    sender = synced(KEY, before_restart)
    capture = [sender.command(Twist(0.5, 0, 0), WALL + 0.05 * i) for i in range(20)]
    assert all(before_restart.datagram(d, MONO + 0.05 * i, WALL + 0.05 * i) for i, d in enumerate(capture))
    # the daemon restarts (a new receiver, the same key); the capture comes back 11 s later, clock check off
    restarted = TeleopReceiver(KEY, max_clock_offset_s=0.0)
    assert restarted.instance != before_restart.instance
    replies = [restarted.datagram(d, MONO + 11.0 + 0.05 * i, WALL + 11.0 + 0.05 * i) for i, d in enumerate(capture)]
    assert not any(isinstance(reply, TeleopCommand | StopCommand) for reply in replies)
    assert restarted.accepted == 0
    assert rejected(restarted) == {"stale_session": 20}


def test_a_stale_client_is_answered_and_drives_again_after_one_round_trip() -> None:
    old, new = TeleopReceiver(KEY), TeleopReceiver(KEY)
    sender = synced(KEY, old)
    refused = sender.command(Twist(0.3, 0, 0), WALL)
    answer = welcome_for(sender, new, refused)
    assert rejected(new) == {"stale_session": 1}
    assert len(answer) <= len(refused)
    assert sender.take_answer(answer)
    assert isinstance(new.datagram(sender.command(Twist(0.3, 0, 0), WALL + 0.05), MONO, WALL), TeleopCommand)
    # a client that never asked (no instance yet) is answered the same way
    fresh = TeleopSender(KEY)
    assert fresh.take_answer(welcome_for(fresh, new, fresh.command(Twist(0.1, 0, 0), WALL)))
    assert fresh.instance == new.instance


def test_the_client_takes_only_genuine_fresh_answers_to_its_own_requests() -> None:
    receiver, sender = TeleopReceiver(KEY), TeleopSender(KEY)
    other_key = TeleopReceiver(b"another-key-of-enough-length")
    hello = sender.hello(WALL)
    # signed with another key, or answering another sender's session: ignored
    assert not sender.take_answer(welcome_for(sender, other_key, TeleopSender(other_key.key).hello(WALL)))
    assert not sender.take_answer(welcome_for(sender, receiver, TeleopSender(KEY).hello(WALL)))
    forged = bytearray(welcome_for(sender, receiver, hello))
    forged[20] ^= 0x01  # another instance, same tag
    assert not sender.take_answer(bytes(forged))
    assert sender.instance != receiver.instance
    first = welcome_for(sender, receiver, hello)
    assert sender.take_answer(first)
    # the daemon restarts; the client re-synchronises; the old answer replayed must not roll it back
    restarted = TeleopReceiver(KEY)
    assert sender.take_answer(welcome_for(sender, restarted, sender.command(Twist(0.1, 0, 0), WALL)))
    assert not sender.take_answer(first)
    assert sender.instance == restarted.instance


def test_hellos_are_checked_like_commands_before_they_are_answered() -> None:
    receiver = TeleopReceiver(KEY)
    assert receiver.datagram(TeleopSender(None).hello(WALL), MONO, WALL) is None
    assert receiver.datagram(TeleopSender(b"another-key-of-enough-length").hello(WALL), MONO, WALL) is None
    odd = bytearray(TeleopSender(KEY).hello(WALL)[:HEADER_SIZE])
    odd[40] = 0x3F  # a hello carries no velocity
    assert receiver.datagram(bytes(odd) + hmac.new(KEY, bytes(odd), sha256).digest(), MONO, WALL) is None
    assert rejected(receiver) == {"unauthenticated": 1, "bad_tag": 1, "malformed": 1}
    assert receiver.counters()["answered"] == 0
    # a client whose clock is an hour off is answered with ours, so that it can say why its commands are refused
    late = TeleopSender(KEY)
    assert late.take_answer(welcome_for(late, receiver, late.hello(WALL - 3600.0)))
    assert late.daemon_time == WALL
    assert receiver.datagram(late.command(Twist(0.1, 0, 0), WALL - 3600.0), MONO, WALL) is None
    assert rejected(receiver)["clock_offset"] == 1
    # without a key, hellos are answered unsigned: anyone can ask (the README says what that protects)
    open_receiver = TeleopReceiver(None, allow_unauthenticated=True)
    sender = TeleopSender(None)
    assert sender.take_answer(welcome_for(sender, open_receiver, sender.hello(WALL)))


def test_answers_to_one_source_are_rate_limited() -> None:
    receiver = TeleopReceiver(KEY)
    sender = TeleopSender(KEY)
    answers = [receiver.datagram(sender.hello(WALL), MONO, WALL, source="flooder") for _ in range(100)]
    assert sum(isinstance(a, Answer) for a in answers) == ANSWERS_PER_S
    assert rejected(receiver) == {"rate_limited": 100 - ANSWERS_PER_S}
    assert isinstance(receiver.datagram(sender.hello(WALL), MONO, WALL, source="someone else"), Answer)
    assert isinstance(receiver.datagram(sender.hello(WALL), MONO + 1.0, WALL, source="flooder"), Answer)
