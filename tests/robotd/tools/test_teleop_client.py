"""The teleop client against the daemon's real receiver on loopback UDP, and its keys on a real pseudo-terminal."""

from __future__ import annotations

import asyncio
import os
import pty
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from robotd.cli import main
from robotd.config.model import TeleopConfig
from robotd.daemon.teleop import Answer, StopCommand, TeleopCommand, TeleopMessage, TeleopReceiver
from robotd.daemon.teleop_socket import TeleopSocket, open_teleop
from robotd.kinematics import Twist
from robotd.tools.teleop_client import STOP, KeyboardState, UdpLink, run_keyboard, square_plan

KEY = b"loopback-test-key-0123456789"


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port: int = probe.getsockname()[1]
        return port


async def test_send_for_drives_then_stops_through_the_real_receiver(tmp_path: Path) -> None:
    key_file = tmp_path / "teleop.key"
    key_file.write_bytes(KEY)
    config = TeleopConfig(bind="127.0.0.1", port=free_udp_port(), key_file=str(key_file))
    receiver = TeleopReceiver.from_config(config, KEY)
    messages: list[TeleopMessage] = []
    transport = await open_teleop(config, receiver, messages.append)
    try:
        argv = ["teleop", "--port", str(config.port), "--key-file", str(key_file), "--rate", "50"]
        status = await asyncio.to_thread(main, [*argv, "--send", "0.3", "-0.1", "0.5", "--for", "0.2"])
        await asyncio.sleep(0.05)
    finally:
        transport.close()
    assert status == 0
    commands = [m for m in messages if isinstance(m, TeleopCommand)]
    assert 8 <= len(commands) <= 12  # 50 Hz for 0.2 s
    assert {c.twist for c in commands} == {Twist(0.3, -0.1, 0.5)}
    assert isinstance(messages[-1], StopCommand)
    assert receiver.counters()["accepted"] == len(messages)
    assert sum(receiver.rejected.values()) == 0


async def test_the_client_says_when_the_robots_clock_is_off(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = TeleopConfig(bind="127.0.0.1", port=free_udp_port(), key_file="unused")
    receiver = TeleopReceiver.from_config(config, KEY)
    raw = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    raw.bind(("127.0.0.1", config.port))
    messages: list[TeleopMessage] = []
    # the robot's clock is a minute behind: beyond max_clock_offset_s, so every command is refused
    robot = TeleopSocket(raw, receiver, messages.append, read_budget_per_s=1e4, wall_clock=lambda: time.time() - 60.0)
    key_file = tmp_path / "teleop.key"
    key_file.write_bytes(KEY)
    try:
        argv = ["teleop", "--port", str(config.port), "--key-file", str(key_file), "--send", "0.1", "0", "0"]
        status = await asyncio.to_thread(main, [*argv, "--for", "0.1"])
    finally:
        robot.close()
    assert status == 0
    assert "the robot's clock is -60.0 s from this computer's" in capsys.readouterr().err
    assert messages == []
    assert receiver.counters()["clock_offset"] > 0


def test_a_client_with_nobody_listening_asks_at_its_pace_and_gives_up() -> None:
    link = UdpLink("127.0.0.1", free_udp_port(), KEY)  # nobody there: each hello comes back as an ICMP error
    try:
        assert not link.sync(0.5, retry_s=0.1)
        assert 3 <= link.sender.sequence <= 6  # one hello each 0.1 s, not a busy loop woken by the errors
        link.send(Twist(0.2, 0.0, 0.0))  # still unsynced: a hello, not a command, and no error
        assert not link.synced
    finally:
        link.sock.close()


def test_the_square_is_four_slides_with_a_stop_after_each() -> None:
    plan = square_plan(3.0, 0.3, loops=2, pause_s=1.0)
    assert len(plan) == 16
    drives = [leg for leg in plan if leg.twist != STOP]
    assert [(leg.twist.vx, leg.twist.vy) for leg in drives[:4]] == [(0.3, 0.0), (0.0, -0.3), (-0.3, 0.0), (0.0, 0.3)]
    assert all(leg.duration_s == pytest.approx(10.0) for leg in drives)
    assert all(leg.twist == STOP and leg.duration_s == 1.0 for leg in plan[1::2])
    with pytest.raises(ValueError, match="side"):
        square_plan(0.0, 0.3, loops=1, pause_s=0.0)


def test_keys_latch_one_motion_and_scale_speed() -> None:
    state = KeyboardState()
    state = state.press("a")
    assert state.twist == Twist(0.0, 0.2, 0.0)
    state = state.press("+")
    assert state.twist.vy == pytest.approx(0.25)
    assert state.linear_mps == pytest.approx(0.25)
    state = state.press("e")
    assert state.twist == Twist(0.0, 0.0, -state.angular_rad_s)
    assert state.press("?") == state
    assert state.press(" ").twist == STOP
    quit_state = state.press("x")
    assert not quit_state.running
    assert quit_state.twist == STOP


class Listener:
    """A bare UDP socket with a receiver: answers hellos like the daemon, hands back the other messages."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(2.0)
        self.port: int = self.sock.getsockname()[1]
        self.receiver = TeleopReceiver(KEY)

    def next_message(self) -> TeleopMessage | None:
        """The next datagram's message (answering hellos on the way); None for a rejected one."""
        while True:
            data, address = self.sock.recvfrom(200)
            outcome = self.receiver.datagram(data, 0.0)
            if not isinstance(outcome, Answer):
                return outcome
            self.sock.sendto(outcome.datagram, address)


def test_interactive_keys_on_a_pseudo_terminal() -> None:
    listener = Listener()
    master, slave = pty.openpty()
    terminal = os.fdopen(slave, "r")
    out_path = os.devnull
    link = UdpLink("127.0.0.1", listener.port, KEY)
    try:
        with open(out_path, "w") as out:
            driver = threading.Thread(target=run_keyboard, args=(link, 20.0, terminal, out))
            driver.start()
            # The first datagram (a hello, then stops) is sent once the terminal is in cbreak mode, which flushes
            # earlier input; the hello is answered and the link sends stops from then on.
            first = listener.next_message()
            while first is None or not isinstance(first, StopCommand):
                first = listener.next_message()
            os.write(master, b"w")
            forward = None
            for _ in range(20):
                message = listener.next_message()
                if isinstance(message, TeleopCommand):
                    forward = message
                    break
            os.write(master, b"x")
            driver.join(timeout=5.0)
            assert not driver.is_alive()
        link.close()  # what the command does on every exit: a final stop
        last = None
        listener.sock.settimeout(0.5)
        while True:
            try:
                last = listener.next_message()
            except TimeoutError:
                break
        assert forward is not None
        assert forward.twist == Twist(0.2, 0.0, 0.0)
        assert isinstance(last, StopCommand)
    finally:
        link.sock.close()  # already closed on success; closing again is harmless
        terminal.close()
        os.close(master)
        listener.sock.close()


async def test_the_client_resyncs_with_a_restarted_receiver_and_drives_again() -> None:
    config = TeleopConfig(bind="127.0.0.1", port=free_udp_port(), key_file="unused")
    first = TeleopReceiver.from_config(config, KEY)
    messages: list[TeleopMessage] = []
    listening = await open_teleop(config, first, messages.append)
    link = UdpLink("127.0.0.1", config.port, KEY)
    try:
        assert await asyncio.to_thread(link.sync, 2.0)
        link.send(Twist(0.2, 0.0, 0.0))
        await wait_until(lambda: len(messages) == 1)
        listening.close()  # the daemon stops; commands meanwhile go nowhere
        link.send(Twist(0.2, 0.0, 0.0))
        restarted = TeleopReceiver.from_config(config, KEY)
        listening = await open_teleop(config, restarted, messages.append)
        # the client goes on at its rate: the first command is refused and answered, a later one drives
        for _ in range(50):
            link.send(Twist(0.3, 0.0, 0.0))
            await asyncio.sleep(0.02)
            if restarted.accepted:
                break
        assert restarted.counters()["stale_session"] >= 1
        assert restarted.accepted >= 1
        assert link.resyncs == 2
        assert isinstance(messages[-1], TeleopCommand)
        assert messages[-1].twist == Twist(0.3, 0.0, 0.0)
    finally:
        listening.close()
        link.sock.close()


async def wait_until(condition: Callable[[], bool], timeout_s: float = 2.0) -> None:
    async with asyncio.timeout(timeout_s):
        while not condition():
            await asyncio.sleep(0.005)
