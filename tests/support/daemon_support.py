"""The daemon end to end: `robotd vhw` and `robotd run` as real processes, watched through their real interfaces.

`Robot` starts both on a private copy of config/sim.yaml (free loopback ports, paths in a temporary folder) and
gives the tests what a person would have: a teleop client on the UDP port, a pose client on the Unix socket, the
real `pigpio` client library on the virtual pigpiod (to read the motor duties), and the simulator's truth record.
"""

from __future__ import annotations

import contextlib
import json
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pigpio
from paths import REPO

from drivers.pigpiod.client import stop_pigpio_client
from robotd.config.model import WHEELS, MotorPins, RobotdConfig, load
from robotd.daemon import poseclient
from robotd.kinematics import Twist
from robotd.tools.demo import Children, private_config
from robotd.tools.teleop_client import UdpLink

SIM_CONFIG = REPO / "config" / "sim.yaml"
START_TIMEOUT_S = 20.0

Duties = tuple[float, float, float, float]
Overrides = dict[str, dict[str, Any]]


def robot_config(out: Path, overrides: Overrides | None = None) -> Path:
    """A private copy of the simulation config in `out`, with some keys of some sections changed."""
    return private_config(SIM_CONFIG, out, overrides)


def wait_until(condition: Callable[[], bool], timeout_s: float, what: str, poll_s: float = 0.01) -> float:
    """Poll `condition` until it holds (returns the time it did) or fail after `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while True:
        if condition():
            return time.monotonic()
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s:g} s waiting for {what}")
        time.sleep(poll_s)


class PoseTap(threading.Thread):
    """A pose client that reads every message as it arrives and keeps the poses and statuses with their arrival."""

    def __init__(self, path: str) -> None:
        super().__init__(name="pose-tap", daemon=True)
        self.sock = poseclient.connect(path)
        self.poses: list[tuple[float, dict[str, Any]]] = []
        self.statuses: list[dict[str, Any]] = []
        self.start()

    def run(self) -> None:
        """Read lines until the daemon hangs up or the tap is closed."""
        with contextlib.suppress(OSError):
            for received in poseclient.messages(self.sock):
                assert received.message is not None, f"the daemon sent a line that is not JSON: {received.line!r}"
                if received.kind == "pose":
                    self.poses.append((received.arrived, received.message))
                elif received.kind == "status":
                    self.statuses.append(received.message)

    @property
    def pose(self) -> dict[str, Any]:
        """The latest pose."""
        return self.poses[-1][1]

    def status_after(self, t: float, timeout_s: float = 5.0) -> dict[str, Any]:
        """The first status message the daemon stamped after monotonic time `t`."""
        found: list[dict[str, Any]] = []

        def arrived() -> bool:
            found[:] = [s for s in self.statuses if s["t"] > t][:1]
            return bool(found)

        wait_until(arrived, timeout_s, f"a status after t={t:.3f}")
        return found[0]

    def close(self) -> None:
        """Hang up and stop reading."""
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)
        self.sock.close()
        self.join(5.0)


def pwm_fraction(pi: Any, gpio: int) -> float:
    """What an L298 input sees on `gpio`: the PWM duty as a fraction of its range, else the steady level."""
    try:
        return float(pi.get_PWM_dutycycle(gpio)) / float(pi.get_PWM_range(gpio))
    except pigpio.error:  # not a PWM output: an output's level, or an input's pull (the motor pins pull down)
        return float(pi.read(gpio))


def channel_duty(pi: Any, pins: MotorPins) -> float:
    """One L298 channel's signed duty as the bridge applies it: enable duty times the direction inputs."""
    direction = int(pi.read(pins.in1)) - int(pi.read(pins.in2))
    return pwm_fraction(pi, pins.enable) * direction * pins.sign


class Robot:
    """The virtual robot and the daemon running, with the clients a test needs (see the module docstring)."""

    def __init__(self, out: Path, overrides: Overrides | None = None, seed: int = 5) -> None:
        self.out = out
        self.config_path = robot_config(out, overrides)
        self.config: RobotdConfig = load(self.config_path)
        self.seed = seed
        self.children = Children()
        self.vhw: subprocess.Popen[str] | None = None
        self.daemon: subprocess.Popen[str] | None = None
        self.tap: PoseTap | None = None
        self.pi: Any = None
        self.link: UdpLink | None = None
        self.motor_pins = [getattr(self.config.motors.wheels, wheel) for wheel in WHEELS]

    # --- processes -------------------------------------------------------------------------------------------

    def start_vhw(self) -> subprocess.Popen[str]:
        """Start `robotd vhw` and wait for its pseudo-terminal link and its pigpiod port."""
        device = Path(self.config.marvelmind.device)
        with contextlib.suppress(FileNotFoundError):
            device.unlink()  # a link left by a killed vhw must not count as a fresh one
        self.vhw = self.children.start(
            "robotd vhw",
            ["vhw", "--config", str(self.config_path), "--seed", str(self.seed)],
            self.out / "vhw.log",
        )
        self._wait(lambda: device.is_symlink() and self._pigpiod_listening(), "the virtual robot")
        if self.pi is None:
            self.pi = pigpio.pi("127.0.0.1", self.config.pigpiod.port, show_errors=False)
            assert self.pi.connected, "the pigpio client could not connect to the virtual pigpiod"
        return self.vhw

    def start_daemon(self) -> subprocess.Popen[str]:
        """Start `robotd run` and attach a pose tap once its socket is there."""
        self.daemon = self.children.start(
            "robotd run", ["run", "--config", str(self.config_path)], self.out / "daemon.log"
        )
        path = Path(self.config.pose_socket.path)
        self._wait(lambda: self._attach_tap(path), "the daemon's pose socket")
        self._wait(lambda: self.tap is not None and bool(self.tap.poses), "the first pose")
        return self.daemon

    def _attach_tap(self, path: Path) -> bool:
        """Attach the pose tap once the daemon accepts there: its socket file appears at bind, a moment before it
        listens, and a busy machine can show the file to a client that is then refused."""
        try:
            self.tap = PoseTap(str(path))
        except (FileNotFoundError, ConnectionRefusedError):
            return False
        return True

    def _pigpiod_listening(self) -> bool:
        with socket.socket() as probe:
            return probe.connect_ex(("127.0.0.1", self.config.pigpiod.port)) == 0

    def _wait(self, condition: Callable[[], bool], what: str) -> None:
        def ready() -> bool:
            for proc in self.children.procs:
                if proc.poll() is not None and proc in (self.vhw, self.daemon):
                    raise AssertionError(f"{proc.args!s} exited with {proc.returncode}: {self.logs()}")
            return condition()

        wait_until(ready, START_TIMEOUT_S, what, poll_s=0.02)

    def logs(self) -> str:
        """The children's output so far, for failure messages."""
        return "\n".join(
            f"--- {name}\n{(self.out / name).read_text(encoding='utf-8', errors='replace')[-3000:]}"
            for name in ("vhw.log", "daemon.log")
            if (self.out / name).exists()
        )

    def signal_vhw(self, signum: signal.Signals) -> None:
        """Send a signal to the virtual robot."""
        assert self.vhw is not None
        self.vhw.send_signal(signum)

    def close(self) -> None:
        """Stop everything this robot started, clients first."""
        if self.link is not None:
            self.link.sock.close()  # no final stop: the daemon may be gone, and the tests send their own
        if self.tap is not None:
            self.tap.close()
        if self.pi is not None:
            stop_pigpio_client(self.pi)
        self.children.stop_all()

    # --- what a person sees and does ---------------------------------------------------------------------------

    def send(self, twist: Twist) -> None:
        """One teleop datagram from this robot's client."""
        if self.link is None:
            self.link = UdpLink("127.0.0.1", self.config.teleop.port, None)
            assert self.link.sync(5.0), "the daemon did not answer the teleop hello"
        self.link.send(twist)

    def drive(self, twist: Twist, duration_s: float, rate_hz: float = 20.0) -> float:
        """Send `twist` at `rate_hz` for `duration_s`; returns the time of the last datagram."""
        start = time.monotonic()
        sent_at = start
        tick = 0
        while sent_at - start < duration_s:
            self.send(twist)
            sent_at = time.monotonic()
            tick += 1
            time.sleep(max(0.0, start + tick / rate_hz - time.monotonic()))
        return sent_at

    def duties(self) -> Duties:
        """The four channels' duties (FL, FR, RL, RR) read from the virtual pigpiod with the real pigpio client."""
        d = [channel_duty(self.pi, pins) for pins in self.motor_pins]
        return (d[0], d[1], d[2], d[3])

    def truth(self) -> list[dict[str, Any]]:
        """The simulator's ground-truth samples recorded so far (complete lines only)."""
        text = Path(self.config.sim.record_path).read_text(encoding="utf-8")
        lines = text.split("\n")[:-1]  # the last piece is empty or a line still being written
        return [event for event in map(json.loads, lines) if event.get("type") == "truth"]

    def daemon_log(self) -> str:
        """The daemon's output so far."""
        return (self.out / "daemon.log").read_text(encoding="utf-8", errors="replace")


@contextlib.contextmanager
def running_robot(out: Path, overrides: Overrides | None = None, seed: int = 5) -> Iterator[Robot]:
    """A `Robot` with both processes up; everything stopped on the way out."""
    robot = Robot(out, overrides, seed)
    try:
        robot.start_vhw()
        robot.start_daemon()
        yield robot
    finally:
        robot.close()
