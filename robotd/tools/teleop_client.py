"""The teleop client: sends commands at a steady rate, from fixed plans (`--send`, `--square`) or terminal keys.

Commands are repeated at `rate_hz` (well inside the daemon's deadman timeout) and every exit path sends an
explicit stop, so a client that quits never leaves the robot driving until the deadman fires.
"""

from __future__ import annotations

import contextlib
import math
import os
import select
import socket
import sys
import termios
import time
import tty
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from typing import TextIO

from robotd.daemon.teleop import DATAGRAM_SIZE, TeleopSender
from robotd.kinematics import Twist

STOP = Twist(0.0, 0.0, 0.0)


@dataclass(frozen=True, slots=True)
class Leg:
    """One step of a plan: drive at `twist` for `duration_s` seconds."""

    twist: Twist
    duration_s: float


def square_plan(side_m: float, speed_mps: float, loops: int, pause_s: float) -> list[Leg]:
    """The paper's square driven open-loop: +x, slide to -y, -x, slide to +y, with a stop after each side."""
    if side_m <= 0 or speed_mps <= 0 or loops < 1 or pause_s < 0:
        raise ValueError("side and speed must be > 0, loops >= 1, pause >= 0")
    # The slew-limited ramps up and down cancel out: a side driven for side/speed covers the side.
    drive = side_m / speed_mps
    directions = [Twist(speed_mps, 0.0, 0.0), Twist(0.0, -speed_mps, 0.0), Twist(-speed_mps, 0.0, 0.0)]
    directions.append(Twist(0.0, speed_mps, 0.0))
    plan: list[Leg] = []
    for _ in range(loops):
        for twist in directions:
            plan += [Leg(twist, drive), Leg(STOP, pause_s)]
    return plan


class UdpLink:
    """A sender session on a connected UDP socket, synchronised with the daemon instance it talks to.

    A command needs the daemon's instance nonce: until a welcome has brought it, `send` sends a hello instead of
    the command. Answers are read (without waiting) before each send, so when the daemon restarts, the welcome
    it sends back for the first refused command re-synchronises the link within one round trip.
    """

    def __init__(self, host: str, port: int, key: bytes | None) -> None:
        self.sender = TeleopSender(key)
        self.sock = socket.socket(socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)[0][0], socket.SOCK_DGRAM)
        self.sock.connect((host, port))
        self.sock.setblocking(False)
        self.resyncs = 0  # times a welcome brought a new daemon instance
        self.clock_offset_s = math.nan  # the daemon's Unix time minus ours, from the latest welcome

    @property
    def synced(self) -> bool:
        """Whether the link knows the daemon's instance (commands can be sent)."""
        return self.sender.instance is not None

    def sync(self, timeout_s: float, retry_s: float = 0.1) -> bool:
        """Ask for the daemon's instance until it answers or `timeout_s` passes; True when the link is synced."""
        now = time.monotonic()
        deadline, next_hello = now + timeout_s, now
        while not self.synced and now < deadline:
            if now >= next_hello:  # paced: an ICMP error wakes the select at once when nobody listens
                self._send(self.sender.hello(time.time()))
                next_hello = now + retry_s
            select.select([self.sock], [], [], max(0.0, min(next_hello, deadline) - now))
            self.take_answers()
            now = time.monotonic()
        return self.synced

    def take_answers(self) -> None:
        """Read the daemon's answers waiting on the socket and adopt a new instance from a genuine one."""
        while True:
            try:
                data = self.sock.recv(DATAGRAM_SIZE + 1)
            except (BlockingIOError, InterruptedError):
                return
            except ConnectionRefusedError:  # an ICMP "port unreachable" for an earlier send: nobody listening
                continue
            if self.sender.take_answer(data):
                self.resyncs += 1
                daemon_time = self.sender.daemon_time
                self.clock_offset_s = daemon_time - time.time() if daemon_time > 0.0 else math.nan

    def send(self, twist: Twist) -> None:
        """Send one command (a stop when the twist is zero), or a hello while the daemon's instance is unknown."""
        self.take_answers()
        if not self.synced:
            self._send(self.sender.hello(time.time()))
        elif twist == STOP:
            self._send(self.sender.stop(time.time()))
        else:
            self._send(self.sender.command(twist, time.time()))

    def _send(self, datagram: bytes) -> None:
        # nobody listening yet, or the socket buffer full: UDP is fire-and-forget, the next send tries again
        with contextlib.suppress(ConnectionRefusedError, BlockingIOError):
            self.sock.send(datagram)

    def close(self) -> None:
        """Send a final stop and close the socket."""
        try:
            self.send(STOP)
        finally:
            self.sock.close()


def run_plan(
    link: UdpLink,
    plan: list[Leg],
    rate_hz: float,
    *,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
    report: Callable[[Leg], None] | None = None,
) -> int:
    """Send each leg's twist at `rate_hz` for its duration, on a fixed schedule; returns the datagrams sent."""
    period, sent = 1.0 / rate_hz, 0
    for leg in plan:
        if report is not None:
            report(leg)
        start = clock()
        tick = 0
        while True:
            link.send(leg.twist)
            sent += 1
            tick += 1
            due = start + tick * period
            if due - start >= leg.duration_s:
                sleep(max(0.0, start + leg.duration_s - clock()))
                break
            sleep(max(0.0, due - clock()))
    return sent


KEY_HELP = "w/s forward/back, a/d strafe left/right, q/e rotate left/right, space stop, +/- speed, x quit"


@dataclass(frozen=True, slots=True)
class KeyboardState:
    """Interactive teleop: one latched motion at a time, at the current speeds."""

    twist: Twist = STOP
    linear_mps: float = 0.2
    angular_rad_s: float = 0.8
    running: bool = True

    def press(self, key: str) -> KeyboardState:
        """The state after one key press (unknown keys change nothing)."""
        lin, ang = self.linear_mps, self.angular_rad_s
        motions = {
            "w": Twist(lin, 0.0, 0.0),
            "s": Twist(-lin, 0.0, 0.0),
            "a": Twist(0.0, lin, 0.0),
            "d": Twist(0.0, -lin, 0.0),
            "q": Twist(0.0, 0.0, ang),
            "e": Twist(0.0, 0.0, -ang),
            " ": STOP,
        }
        key = key.lower()
        if key in motions:
            return replace(self, twist=motions[key])
        if key in ("+", "=", "-", "_"):
            factor = 1.25 if key in ("+", "=") else 0.8
            scaled = replace(self, linear_mps=min(2.0, lin * factor), angular_rad_s=min(8.0, ang * factor))
            return replace(scaled, twist=_rescaled(self, scaled))
        if key in ("x", "\x1b", "\x04"):  # x, Escape, Ctrl-D
            return replace(self, twist=STOP, running=False)
        return self

    def line(self) -> str:
        """One status line for the terminal."""
        t = self.twist
        return (
            f"vx {t.vx:+.2f} m/s  vy {t.vy:+.2f} m/s  wz {t.wz:+.2f} rad/s   "
            f"speed {self.linear_mps:.2f} m/s {self.angular_rad_s:.2f} rad/s"
        )


def _rescaled(old: KeyboardState, new: KeyboardState) -> Twist:
    """The latched motion at the new speeds."""
    lin = new.linear_mps / old.linear_mps
    ang = new.angular_rad_s / old.angular_rad_s
    return Twist(old.twist.vx * lin, old.twist.vy * lin, old.twist.wz * ang)


@contextlib.contextmanager
def cbreak(fd: int) -> Iterator[None]:
    """Keys arrive one at a time, unechoed; Ctrl-C still interrupts; the terminal is restored on every exit."""
    saved = termios.tcgetattr(fd)
    try:
        tty.setcbreak(fd)
        yield
    finally:
        termios.tcsetattr(fd, termios.TCSADRAIN, saved)


def run_keyboard(link: UdpLink, rate_hz: float, terminal: TextIO = sys.stdin, out: TextIO = sys.stdout) -> int:
    """Drive from terminal keys until x/Escape/Ctrl-D, re-sending the latched motion at `rate_hz`."""
    fd = terminal.fileno()
    state = KeyboardState()
    print(KEY_HELP, file=out)
    period = 1.0 / rate_hz
    with cbreak(fd):
        next_send = time.monotonic()
        while state.running:
            readable, _, _ = select.select([fd], [], [], max(0.0, next_send - time.monotonic()))
            if readable:
                keys = os.read(fd, 64).decode(errors="replace")
                if not keys:  # end of input: the terminal went away
                    break
                for key in keys:
                    state = state.press(key)
                link.send(state.twist)  # a key acts at once, not at the next tick
                print(f"\r{state.line()}\x1b[K", end="", file=out, flush=True)
            if time.monotonic() >= next_send:
                link.send(state.twist)
                next_send = max(next_send + period, time.monotonic())
    print(file=out)
    return 0
