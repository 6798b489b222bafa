"""The wheels stop however `robotd run` dies or stalls: SIGKILL and SIGSTOP are caught by the deadman script in
(virtual) pigpiod, SIGHUP and SIGQUIT end the daemon cleanly; every transition keeps the L298 bridge rule, and the
motor pins are left outputs driven low (real processes and sockets).

Most runs use a virtual pigpiod in this process, so the tests read its pin history (who wrote which pin when) and
see that it was the script that stopped the motors; the daemon runs without the rest of the virtual robot (no
physics, no beacon), which the motor path does not need. One run uses the whole virtual robot (`robotd vhw`).
"""

from __future__ import annotations

import contextlib
import signal
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pigpio
import pytest
from daemon_support import robot_config, running_robot, wait_until

from drivers.pigpiod.client import stop_pigpio_client
from drivers.pigpiod.deadman import TRIPS, find_deadmen
from drivers.pigpiod.protocol import Mode
from drivers.virtual.l298 import Channel, bridge_rule_violations
from drivers.virtual.pigpiod import VirtualPigpiod
from drivers.virtual.pins import PinWrite
from drivers.wheels.motors import enable_and_direction_pins
from robotd.config.model import WHEELS, MotorPins, RobotdConfig, load
from robotd.kinematics import Twist
from robotd.tools.demo import Children
from robotd.tools.teleop_client import UdpLink

pytestmark = pytest.mark.slow

FORWARD = Twist(0.3, 0.0, 0.0)
REVERSE = Twist(-0.3, 0.0, 0.0)
STOP = Twist(0.0, 0.0, 0.0)
LATERAL = Twist(0.0, 0.3, 0.0)
ROTATE = Twist(0.0, 0.0, 1.0)
STOP_BOUND_S = 3.0
"""A generous functional bound, on top of the deadman timeout, for the pins to go low (`robotd bench daemon` has
the figure)."""


class BareDaemon:
    """`robotd run` (started and restarted at will) on a virtual pigpiod of this process, with a teleop client."""

    def __init__(self, out: Path, server: VirtualPigpiod) -> None:
        self.out, self.server = out, server
        # no physics turns the wheels here: the stall guard (it stops wheels that never turn) gets its longest timeout
        self.config_path = robot_config(out, {"pigpiod": {"port": server.port}, "control": {"stall_timeout_s": 5.0}})
        self.config: RobotdConfig = load(self.config_path)
        self.pins: list[MotorPins] = [getattr(self.config.motors.wheels, wheel) for wheel in WHEELS]
        enables, directions = enable_and_direction_pins(self.config.motors)
        self.motor_gpios = [*enables, *directions]
        self.children = Children()
        self.proc: subprocess.Popen[str] | None = None
        self.log_path = out / "daemon.log"
        self.link = UdpLink("127.0.0.1", self.config.teleop.port, None)
        self.pi: Any = pigpio.pi("127.0.0.1", server.port, show_errors=False)

    def start(self, name: str = "daemon") -> subprocess.Popen[str]:
        """Start `robotd run`; returns once it says it is running."""
        self.log_path = self.out / f"{name}.log"
        self.proc = self.children.start("robotd run", ["run", "--config", str(self.config_path)], self.log_path)
        proc = self.proc

        def running() -> bool:
            assert proc.poll() is None, f"robotd run exited with {proc.returncode}: {self.log()}"
            return "robotd running" in self.log()

        wait_until(running, 20.0, "the daemon to run", poll_s=0.02)
        return proc

    def log(self) -> str:
        return self.log_path.read_text(encoding="utf-8", errors="replace") if self.log_path.exists() else ""

    def drive(self, twist: Twist, seconds: float) -> None:
        """Teleop at 20 Hz for a while."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.link.send(twist)
            time.sleep(0.05)

    def duties(self) -> list[float]:
        """Each channel's signed duty as the bridge applies it."""
        level, duty = self.server.level, self.server.pwm_duty
        return [duty(p.enable) * (level(p.in1) - level(p.in2)) for p in self.pins]

    def all_low(self) -> bool:
        """Every motor pin an output at level 0 (PWM stopped or at duty 0)."""
        server = self.server
        return all(
            server.mode(g) == Mode.OUTPUT and server.level(g) == 0 and server.pwm_duty(g) == 0.0
            for g in self.motor_gpios
        )

    def writes_since(self, t: float) -> list[PinWrite]:
        return [write for write in self.server.pin_history(set(self.motor_gpios)) if write.t >= t]

    def bridge_violations(self) -> list[str]:
        channels = [Channel(p.enable, p.in1, p.in2) for p in self.pins]
        return bridge_rule_violations(self.server.pin_history(), channels)

    def close(self) -> None:
        self.link.sock.close()
        stop_pigpio_client(self.pi)
        self.children.stop_all()


@contextlib.contextmanager
def bare_daemon(out: Path) -> Iterator[BareDaemon]:
    """A virtual pigpiod here and `robotd run` on it; everything stopped on the way out."""
    with VirtualPigpiod() as server:
        daemon = BareDaemon(out, server)
        try:
            yield daemon
        finally:
            daemon.close()


def assert_the_script_stopped_every_motor_pin(daemon: BareDaemon, since: float) -> None:
    """The deadman script wrote the motor pins after `since`, each low, enables first, and nothing else wrote them
    after its first write.

    Commands the daemon sent before it stopped may still be read after `since`: the virtual pigpiod reads its sockets
    on a thread of this process, which a busy machine delays (a drive's last PWM writes landed just after a SIGKILL).
    """
    writes = daemon.writes_since(since)
    first = next((i for i, write in enumerate(writes) if write.source == "script 0"), None)
    assert first is not None, [(w.source, w.command, w.gpio) for w in writes]
    by_script = writes[first:]
    assert {write.source for write in by_script} == {"script 0"}, [(w.source, w.command, w.gpio) for w in by_script]
    assert [write.gpio for write in by_script[:12]] == daemon.motor_gpios
    assert by_script[0].t - since <= daemon.config.teleop.deadman_timeout_s + STOP_BOUND_S


def test_a_drive_sequence_a_sigstop_and_a_sighup_keep_the_bridge_rule_and_leave_the_pins_low(tmp_path: Path) -> None:
    with bare_daemon(tmp_path) as daemon:
        proc = daemon.start()
        for twist in (FORWARD, REVERSE, STOP, LATERAL, ROTATE):
            daemon.drive(twist, 0.5)
            assert any(daemon.duties()) == (twist != STOP), f"{twist} did not drive as commanded"
        deadman_s = daemon.config.teleop.deadman_timeout_s
        wait_until(lambda: not any(daemon.duties()), deadman_s + STOP_BOUND_S, "the teleop deadman")

        daemon.drive(FORWARD, 0.5)
        assert any(daemon.duties()), "the robot was not driving"
        proc.send_signal(signal.SIGSTOP)
        stopped = time.monotonic()
        try:
            wait_until(daemon.all_low, deadman_s + STOP_BOUND_S, "the deadman script to stop the motors")
            assert_the_script_stopped_every_motor_pin(daemon, stopped)
        finally:
            proc.send_signal(signal.SIGCONT)
        resumed = time.monotonic()
        wait_until(lambda: "deadman stopped the motors" in daemon.log(), 5.0, "the daemon to notice the trip")
        while time.monotonic() < resumed + 1.0:  # its last command is old: a resumed daemon must not drive on it
            assert not any(daemon.duties()), "the daemon drove again without a fresh command"
            time.sleep(0.02)
        daemon.drive(FORWARD, 0.3)
        assert any(daemon.duties()), "a fresh command did not drive after the trip"

        proc.send_signal(signal.SIGHUP)
        assert proc.wait(timeout=10.0) == 0, daemon.log()
        assert "stopping on signal SIGHUP" in daemon.log()
        assert daemon.all_low(), "the motor pins were not left outputs driven low"
        assert find_deadmen(daemon.pi, daemon.motor_gpios) == [], "the deadman script was left in pigpiod"
        assert daemon.bridge_violations() == []
        assert "Traceback" not in daemon.log()


def test_sigkill_is_caught_by_the_deadman_and_the_next_daemon_removes_it_and_ends_cleanly_on_sigquit(
    tmp_path: Path,
) -> None:
    with bare_daemon(tmp_path) as daemon:
        first = daemon.start("first")
        daemon.drive(FORWARD, 0.5)
        assert any(daemon.duties()), "the robot was not driving"
        first.kill()
        killed = time.monotonic()
        first.wait()
        deadman_s = daemon.config.teleop.deadman_timeout_s
        wait_until(daemon.all_low, deadman_s + STOP_BOUND_S, "the deadman script to stop the motors")
        assert_the_script_stopped_every_motor_pin(daemon, killed)
        assert find_deadmen(daemon.pi, daemon.motor_gpios) == [0], "the killed daemon's deadman is not running"

        second = daemon.start("second")
        assert find_deadmen(daemon.pi, daemon.motor_gpios) == [0], "the stale deadman was not replaced by a new one"
        daemon.drive(FORWARD, 0.5)
        assert any(daemon.duties()), "the new daemon does not drive"

        daemon.pi.delete_script(0)  # the deadman lost behind the daemon's back: motors and deadman come back together
        wait_until(lambda: "motor outputs reconnected" in daemon.log(), 10.0, "the daemon to reconnect")
        assert "pigpiod deadman lost" in daemon.log()
        assert len(find_deadmen(daemon.pi, daemon.motor_gpios)) == 1, "no deadman guards the reconnected motors"
        assert second.poll() is None
        second.send_signal(signal.SIGQUIT)
        assert second.wait(timeout=10.0) == 0, daemon.log()
        assert "stopping on signal SIGQUIT" in daemon.log()
        assert daemon.all_low()
        assert find_deadmen(daemon.pi, daemon.motor_gpios) == []
        assert daemon.bridge_violations() == []


def test_on_the_virtual_robot_a_killed_daemon_has_its_wheels_stopped_by_the_deadman(tmp_path: Path) -> None:
    with running_robot(tmp_path) as robot:
        assert robot.daemon is not None
        robot.drive(Twist(0.2, 0.0, 0.0), 0.5)
        assert any(robot.duties()), "the robot was not driving"
        robot.daemon.kill()
        robot.daemon.wait()
        deadman_s = robot.config.teleop.deadman_timeout_s
        wait_until(lambda: not any(robot.duties()), deadman_s + STOP_BOUND_S, "the wheels to stop")
        enables, directions = enable_and_direction_pins(robot.config.motors)
        (script_id,) = find_deadmen(robot.pi, [*enables, *directions])
        assert robot.pi.script_status(script_id)[1][TRIPS] == 1, "the wheels were not stopped by the deadman script"
