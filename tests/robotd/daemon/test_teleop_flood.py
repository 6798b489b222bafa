"""Flood resistance: per-source token buckets, the socket's bounded batches and read budget, the command throttle."""

from __future__ import annotations

import asyncio
import socket
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field

import pytest

from robotd.config.model import ControlConfig, RobotdConfig, TeleopConfig
from robotd.daemon.ratelimit import SourceRateLimiter, TokenBucket
from robotd.daemon.service import Daemon
from robotd.daemon.teleop import BURST_S, TeleopCommand, TeleopMessage, TeleopReceiver, TeleopSender
from robotd.daemon.teleop_socket import BATCH, FLOOD_REPORT_S, TeleopSocket
from robotd.kinematics import Twist

KEY = b"flood-test-key-0123456789abcdef"
WALL = 1_700_000_000.0


def test_a_bucket_allows_its_burst_then_its_rate() -> None:
    bucket = TokenBucket(rate_per_s=10.0, burst=3.0, now=0.0)
    assert [bucket.take(0.0) for _ in range(4)] == [True, True, True, False]
    assert not bucket.take(0.05)  # half a token
    assert bucket.take(0.1)
    assert [bucket.take(10.0) for _ in range(4)] == [True, True, True, False]  # never more than the burst
    assert not bucket.take(5.0)  # a clock step backwards refills nothing and drains nothing
    with pytest.raises(ValueError, match="burst"):
        TokenBucket(rate_per_s=10.0, burst=0.5, now=0.0)


def test_the_limit_holds_each_source_to_its_rate_and_leaves_the_others_alone() -> None:
    limiter = SourceRateLimiter(rate_per_s=100.0, burst=10.0, max_sources=8)
    # a flooder sends 1000 datagrams a second for two seconds (a fake clock), a client 20 a second meanwhile
    flooder = sum(limiter.admit("10.0.0.66", i / 1000.0) for i in range(2000))
    client = sum(limiter.admit("10.0.0.7", i / 20.0) for i in range(40))
    assert flooder == pytest.approx(10 + 100 * 2, abs=2)  # its burst, then its rate
    assert client == 40


def test_the_source_table_is_bounded_and_forgets_the_least_recently_seen() -> None:
    limiter = SourceRateLimiter(rate_per_s=1.0, burst=1.0, max_sources=3)
    for source in ("a", "b", "c"):
        assert limiter.admit(source, 0.0)
    assert not limiter.admit("a", 0.0)  # "a" is now the most recently seen
    assert limiter.admit("d", 0.0)  # evicts "b", the least recently seen
    assert len(limiter) == 3
    assert "b" not in limiter
    assert "a" in limiter
    assert limiter.evicted == 1


def test_the_receiver_limits_a_source_before_parsing_anything() -> None:
    config = TeleopConfig(key_file="", max_datagrams_per_s=50.0)
    receiver = TeleopReceiver.from_config(config, KEY)
    burst = int(50.0 * BURST_S)
    for _ in range(100):
        receiver.datagram(b"junk", 0.0, WALL, source="10.0.0.66")
    counts = receiver.counters()
    assert counts["malformed"] == burst  # only the burst was looked at
    assert counts["rate_limited"] == 100 - burst
    sender = TeleopSender(KEY, instance=receiver.instance)
    command = sender.command(Twist(0.1, 0.0, 0.0), WALL)
    assert isinstance(receiver.datagram(command, 0.0, WALL, source="10.0.0.7"), TeleopCommand)


# --- the socket on a real loopback UDP port ----------------------------------------------------------------------


@dataclass
class Listening:
    """A receiver behind a real TeleopSocket on 127.0.0.1, and what it handed on."""

    receiver: TeleopReceiver
    sock: TeleopSocket
    port: int
    messages: list[TeleopMessage] = field(default_factory=list)


async def listening(receiver: TeleopReceiver, read_budget_per_s: float = 1e6) -> Listening:
    raw = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    raw.bind(("127.0.0.1", 0))
    messages: list[TeleopMessage] = []
    sock = TeleopSocket(raw, receiver, messages.append, read_budget_per_s=read_budget_per_s)
    return Listening(receiver, sock, raw.getsockname()[1], messages)


@pytest.fixture
async def keyless() -> AsyncIterator[Listening]:
    config = TeleopConfig(key_file="", allow_unauthenticated=True, max_datagrams_per_s=100.0)
    listener = await listening(TeleopReceiver.from_config(config, None))
    yield listener
    listener.sock.close()


async def wait_for(condition: Callable[[], bool], what: str, timeout_s: float = 5.0) -> None:
    async with asyncio.timeout(timeout_s):
        while not condition():
            await asyncio.sleep(0.005)
    assert condition(), what


def sender_socket(address: str, port: int) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind((address, 0))
    sock.connect(("127.0.0.1", port))
    return sock


def seen(receiver: TeleopReceiver) -> int:
    """Datagrams the receiver has looked at (counted one way or another)."""
    return sum(n for name, n in receiver.counters().items() if name not in ("answered", "read_pauses"))


async def send_paced(sock: socket.socket, datagrams: list[bytes], receiver: TeleopReceiver, chunk: int = 100) -> None:
    """Send in chunks, each once the receiver has read the last: no datagram is lost to a full socket buffer."""
    start = seen(receiver)
    for first in range(0, len(datagrams), chunk):
        for datagram in datagrams[first : first + chunk]:
            sock.send(datagram)
        expected = start + min(first + chunk, len(datagrams))
        await wait_for(lambda: seen(receiver) >= expected, f"{expected - start} datagrams read")  # noqa: B023


async def test_a_flooding_address_is_limited_while_another_address_drives(keyless: Listening) -> None:
    receiver = keyless.receiver
    client_sender = TeleopSender(None, instance=receiver.instance)
    with sender_socket("127.0.0.2", keyless.port) as flooder, sender_socket("127.0.0.1", keyless.port) as client:
        await send_paced(flooder, [b"junk"] * 2000, receiver)
        client.send(client_sender.command(Twist(0.2, 0.0, 0.0), time.time()))
        await wait_for(lambda: any(isinstance(m, TeleopCommand) for m in keyless.messages), "the client's command")
    counts = receiver.counters()
    assert counts["rate_limited"] >= 2000 - 100 * BURST_S - 100 * 5.0  # the burst, and at most 5 s of the rate
    assert counts["malformed"] == 2000 - counts["rate_limited"]
    assert counts["accepted"] == 1


async def test_the_socket_reads_at_most_a_batch_between_two_loop_iterations(keyless: Listening) -> None:
    loop = asyncio.get_running_loop()
    read_per_iteration = [0]
    counting = keyless.receiver.datagram

    def datagram(*args: object, **kwargs: object) -> object:
        read_per_iteration[-1] += 1
        return counting(*args, **kwargs)  # type: ignore[arg-type]

    keyless.receiver.datagram = datagram  # type: ignore[assignment, method-assign]
    ticking = True

    def tick() -> None:  # runs once per loop iteration while the test waits
        if ticking:
            read_per_iteration.append(0)
            loop.call_soon(tick)

    with sender_socket("127.0.0.1", keyless.port) as flooder:
        for _ in range(200):  # a few hundred queue on any system's default socket buffer
            flooder.send(b"junk")
    tick()
    await wait_for(lambda: sum(read_per_iteration) >= 200, "every datagram read")
    ticking = False
    assert max(read_per_iteration) <= BATCH
    assert max(read_per_iteration) > 1  # several a wake-up: asyncio's own transport reads one
    assert sum(read_per_iteration) == 200


async def test_a_spent_read_budget_pauses_reading_then_reading_resumes() -> None:
    config = TeleopConfig(key_file="", allow_unauthenticated=True)
    receiver = TeleopReceiver.from_config(config, None)
    listener = await listening(receiver, read_budget_per_s=2000.0)
    try:
        with sender_socket("127.0.0.2", listener.port) as flooder:
            await send_paced(flooder, [b"junk"] * 1000, receiver)
        assert receiver.read_pauses >= 1
        client_sender = TeleopSender(None, instance=receiver.instance)
        with sender_socket("127.0.0.1", listener.port) as client:
            client.send(client_sender.command(Twist(0.2, 0.0, 0.0), time.time()))
            await wait_for(lambda: bool(listener.messages), "a command after the pause")
    finally:
        listener.sock.close()


async def test_an_unwatched_socket_is_read_only_when_polled_and_a_watched_one_on_arrival(keyless: Listening) -> None:
    sender = TeleopSender(None, instance=keyless.receiver.instance)
    with sender_socket("127.0.0.1", keyless.port) as client:
        keyless.sock.watch(False)
        client.send(sender.command(Twist(0.1, 0.0, 0.0), time.time()))
        client.send(sender.command(Twist(0.2, 0.0, 0.0), time.time()))
        await asyncio.sleep(0.2)  # time enough for the loop to have read them, were it watching
        assert keyless.messages == []
        keyless.sock.poll()
        assert [message.twist.vx for message in keyless.messages if isinstance(message, TeleopCommand)] == [0.1, 0.2]
        keyless.sock.watch(True)
        client.send(sender.command(Twist(0.3, 0.0, 0.0), time.time()))
        await wait_for(lambda: len(keyless.messages) == 3, "a command read on arrival once watched again")


async def test_a_polled_socket_whose_budget_is_spent_reads_nothing_until_it_refills() -> None:
    config = TeleopConfig(key_file="", allow_unauthenticated=True)
    receiver = TeleopReceiver.from_config(config, None)
    listener = await listening(receiver, read_budget_per_s=2000.0)  # a burst of 100 datagrams
    try:
        listener.sock.watch(False)
        with sender_socket("127.0.0.2", listener.port) as flooder:
            for _ in range(300):
                flooder.send(b"junk")
            await asyncio.sleep(0.05)
            for _ in range(10):
                listener.sock.poll()
            read_before_refill = seen(receiver)
            assert BATCH <= read_before_refill <= 100 + BATCH  # the budget's burst, a batch a poll
            assert receiver.read_pauses == 1
            listener.sock.poll()
            assert seen(receiver) == read_before_refill  # paused: a poll reads nothing
            await wait_for(lambda: listener.sock._resume is None, "the budget refilled")
            listener.sock.poll()
            assert seen(receiver) > read_before_refill
    finally:
        listener.sock.close()


# --- the daemon: a flood of valid commands does not run the controller at its rate ------------------------------


class Clock:
    """A clock the test moves by hand."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


class NoEncoders:
    """An encoder source that never publishes (the daemon's run loop is not started here)."""

    counters = None

    async def run(self, on_ticks: object) -> None:
        """Never called in these tests."""


def test_valid_commands_step_the_controller_at_most_once_per_half_period() -> None:
    clock = Clock()
    # (no encoder publishes here: the stall guard, which would stop a wheel that never turns after its timeout, is
    # given its longest timeout so that the second of commands below is all throttling)
    config = RobotdConfig(
        teleop=TeleopConfig(key_file="", allow_unauthenticated=True), control=ControlConfig(stall_timeout_s=5.0)
    )
    daemon = Daemon(config, clock=clock, encoders=NoEncoders())  # type: ignore[arg-type]
    period = daemon.controller.period_s
    # one second of valid commands at 10 kHz, handed to the daemon's callback as the socket would
    for i in range(10_000):
        clock.now = 100.0 + i * 1e-4
        daemon._on_teleop(TeleopCommand(Twist(0.2, 0.0, 0.0), 7, i + 1, clock.now))
    steps = daemon._counters["control_steps"]  # the count the status message reports
    assert daemon._counters["teleop_commands"] == 10_000
    assert steps <= 1.0 / (0.5 * period) + 1
    assert steps >= 1.0 / period  # yet every half period the newest command steps it at once
    assert daemon.controller.last.setpoint.vx > 0.0


class PolledSocket:
    """What the daemon asks of its teleop socket when the loop reads it itself (the wheels driven)."""

    watching = False


def test_a_command_the_driving_loop_read_itself_does_not_step_the_controller_again() -> None:
    clock = Clock()
    config = RobotdConfig(teleop=TeleopConfig(key_file="", allow_unauthenticated=True))
    daemon = Daemon(config, clock=clock, encoders=NoEncoders())  # type: ignore[arg-type]
    daemon._teleop_socket = PolledSocket()  # type: ignore[assignment]
    for i in range(100):
        clock.now = 100.0 + i * 0.05
        daemon._on_teleop(TeleopCommand(Twist(0.2, 0.0, 0.0), 7, i + 1, clock.now))
    assert daemon._counters["teleop_commands"] == 100
    assert daemon._counters["control_steps"] == 0  # the loop's period steps with it
    assert daemon._teleop.twist == Twist(0.2, 0.0, 0.0)
    assert daemon._teleop.received_at == clock.now


async def test_a_flood_is_reported_in_the_log_at_most_every_ten_seconds(caplog: pytest.LogCaptureFixture) -> None:
    clock = Clock()
    config = TeleopConfig(key_file="", allow_unauthenticated=True, max_datagrams_per_s=10.0)
    receiver = TeleopReceiver.from_config(config, None)
    raw = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    raw.bind(("127.0.0.1", 0))
    listener = TeleopSocket(raw, receiver, lambda _message: None, read_budget_per_s=1e6, clock=clock)
    try:
        with sender_socket("127.0.0.1", raw.getsockname()[1]) as flooder:
            await send_paced(flooder, [b"junk"] * 100, receiver)
            assert "teleop flood" not in caplog.text  # nothing said before FLOOD_REPORT_S
            clock.now += FLOOD_REPORT_S
            await send_paced(flooder, [b"junk"], receiver)
            assert "teleop flood: 98 datagrams over the per-source rate" in caplog.text
            caplog.clear()
            clock.now += 1.0
            await send_paced(flooder, [b"junk"] * 10, receiver)
            assert "teleop flood" not in caplog.text
    finally:
        listener.close()
