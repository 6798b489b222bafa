"""The teleop client against the daemon's real receiver on loopback UDP, and its keys on a real pseudo-terminal."""

from __future__ import annotations

import asyncio
import os
import pty
import socket
import threading
from pathlib import Path

import pytest

from robotd.cli import main
from robotd.config import TeleopConfig
from robotd.kinematics import Twist
from robotd.teleop import StopCommand, TeleopCommand, TeleopMessage, TeleopReceiver, open_teleop
from robotd.teleop_client import STOP, KeyboardState, UdpLink, run_keyboard, square_plan

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


def test_interactive_keys_on_a_pseudo_terminal() -> None:
    listener = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    listener.bind(("127.0.0.1", 0))
    listener.settimeout(2.0)
    master, slave = pty.openpty()
    terminal = os.fdopen(slave, "r")
    out_path = os.devnull
    link = UdpLink("127.0.0.1", listener.getsockname()[1], KEY)
    receiver = TeleopReceiver(KEY)
    try:
        with open(out_path, "w") as out:
            driver = threading.Thread(target=run_keyboard, args=(link, 20.0, terminal, out))
            driver.start()
            # The first datagram (a stop) is sent once the terminal is in cbreak mode, which flushes earlier input.
            assert isinstance(receiver.datagram(listener.recv(100), 0.0), StopCommand)
            os.write(master, b"w")
            forward = None
            for _ in range(20):
                message = receiver.datagram(listener.recv(100), 0.0)
                if isinstance(message, TeleopCommand):
                    forward = message
                    break
            os.write(master, b"x")
            driver.join(timeout=5.0)
            assert not driver.is_alive()
        link.close()  # what the command does on every exit: a final stop
        last = None
        listener.settimeout(0.5)
        while True:
            try:
                last = receiver.datagram(listener.recv(100), 0.0)
            except TimeoutError:
                break
        assert forward is not None
        assert forward.twist == Twist(0.2, 0.0, 0.0)
        assert isinstance(last, StopCommand)
    finally:
        link.sock.close()  # already closed on success; closing again is harmless
        terminal.close()
        os.close(master)
        listener.close()
