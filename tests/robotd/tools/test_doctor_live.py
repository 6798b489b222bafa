"""The doctor against the virtual robot: the real pigpio back-end on the virtual pigpiod in-process, then `robotd
doctor --spin` as a real process beside `robotd vhw` (with `robotd run`, as `robotd sim` runs them), wired right and
wired wrong.
"""

from __future__ import annotations

import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pigpio
import pytest
from paths import REPO

from drivers.pigpiod.client import stop_pigpio_client
from drivers.pigpiod.protocol import Mode
from drivers.virtual.pigpiod import VirtualPigpiod
from robotd.config.model import WHEELS, RobotdConfig, load, parse
from robotd.kinematics import Twist
from robotd.tools.demo import Children, private_config
from robotd.tools.doctor_pigpio import PigpioWheelDrive, pin_modes, reach
from robotd.tools.gpio_backend import BACKEND_NAMES, BackendUnavailableError, backends
from robotd.tools.teleop_client import UdpLink

START_TIMEOUT_S = 20.0


@pytest.fixture
def vpigpiod() -> Iterator[VirtualPigpiod]:
    with VirtualPigpiod() as server:
        yield server


def config_at(port: int, extra: str = "") -> RobotdConfig:
    return parse(f"pigpiod: {{port: {port}}}\n{extra}")


def pins_now(pi: Any, gpio: int) -> tuple[int, int]:
    """(mode, level) of a pin, read with the real pigpio client."""
    return pi.get_mode(gpio), pi.read(gpio)


@pytest.mark.timeout(30)
def test_the_pigpio_back_end_drives_one_wheel_and_leaves_every_motor_pin_low(vpigpiod: VirtualPigpiod) -> None:
    config = config_at(vpigpiod.port, "motors: {wheels: {front_right: {enable: 13, in1: 21, in2: 26, sign: -1}}}\n")
    assert reach(config).startswith(f"pigpiod 79 at 127.0.0.1:{vpigpiod.port}")
    pi: Any = pigpio.pi("127.0.0.1", vpigpiod.port, show_errors=False)
    try:
        drive = PigpioWheelDrive(config)
        drive.drive(1, 0.5)  # front_right, whose motor is configured reversed (sign -1)
        assert pi.get_PWM_dutycycle(13) / pi.get_PWM_range(13) == pytest.approx(0.5, abs=0.01)
        assert (pi.read(21), pi.read(26)) == (0, 1)
        assert pi.read(12) == 0  # front_left's enable: off
        drive.drive(0, 0.4)
        assert pi.get_PWM_dutycycle(12) / pi.get_PWM_range(12) == pytest.approx(0.4, abs=0.01)
        assert pi.read(13) == 0  # only one wheel at a time
        drive.close()
        for wheel in WHEELS:
            pins = getattr(config.motors.wheels, wheel)
            for gpio in (pins.enable, pins.in1, pins.in2):
                assert pins_now(pi, gpio) == (Mode.OUTPUT, 0), (wheel, gpio)  # as robotd stop-motors leaves them
        modes = pin_modes(config, [2, 12])
        assert modes == {2: "input", 12: "output"}
    finally:
        stop_pigpio_client(pi)


def test_the_pigpio_back_end_says_how_to_start_pigpiod_when_absent() -> None:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    with pytest.raises(BackendUnavailableError) as raised:
        reach(config_at(port))
    assert f"pigpiod does not answer at 127.0.0.1:{port}" in raised.value.detail
    assert "sudo systemctl enable --now pigpiod" in raised.value.fix


def test_the_command_line_offers_every_back_end_the_doctor_knows() -> None:
    assert tuple(backends()) == BACKEND_NAMES


# --- real processes --------------------------------------------------------------------------------------------


class VirtualRobot:
    """`robotd vhw` (and optionally `robotd run`) as child processes on a private copy of config/sim.yaml."""

    def __init__(self, out: Path) -> None:
        # no beacon outages: the doctor listens for a few seconds and must hear the beacon in them
        self.config_path = private_config(REPO / "config/sim.yaml", out, {"sim": {"ips_outage_rate_per_min": 0}})
        self.config = load(self.config_path)
        self.out = out
        self.children = Children()

    def wait(self, ready: Any, what: str) -> None:
        deadline = time.monotonic() + START_TIMEOUT_S
        while not ready():
            for proc in self.children.procs:
                assert proc.poll() is None, f"{proc.args!r} exited: {self.logs()}"
            assert time.monotonic() < deadline, f"timed out waiting for {what}: {self.logs()}"
            time.sleep(0.05)

    def start_vhw(self, *wiring: str) -> None:
        self.children.start("robotd vhw", ["vhw", "--config", str(self.config_path), *wiring], self.out / "vhw.log")

        def listening() -> bool:
            with socket.socket() as probe:
                return probe.connect_ex(("127.0.0.1", self.config.pigpiod.port)) == 0

        self.wait(lambda: Path(self.config.marvelmind.device).is_symlink() and listening(), "the virtual robot")

    def start_daemon(self) -> None:
        self.children.start("robotd run", ["run", "--config", str(self.config_path)], self.out / "run.log")
        self.wait(lambda: Path(self.config.pose_socket.path).exists(), "the daemon's pose socket")

    def doctor(self, *argv: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "robotd", "doctor", "--config", str(self.config_path), *argv],
            capture_output=True,
            text=True,
            stdin=subprocess.DEVNULL,
            timeout=60,
            check=False,
        )

    def logs(self) -> str:
        return "\n".join(p.read_text(errors="replace")[-2000:] for p in sorted(self.out.glob("*.log")))


@pytest.fixture
def robot(tmp_path: Path) -> Iterator[VirtualRobot]:
    virtual = VirtualRobot(tmp_path)
    try:
        yield virtual
    finally:
        virtual.children.stop_all()


def verdict_lines(out: str) -> dict[str, str]:
    """'PASS  beacon stream: ...' lines by check name -> verdict."""
    found = {}
    for line in out.splitlines():
        verdict, _, rest = line.partition("  ")
        if verdict in ("PASS", "FAIL", "SKIP") and ":" in rest:
            found[rest.split(":", 1)[0]] = verdict
    return found


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_doctor_spin_beside_the_virtual_robot_and_daemon_passes_and_leaves_the_daemon_driving(
    robot: VirtualRobot,
) -> None:
    robot.start_vhw()
    robot.start_daemon()
    result = robot.doctor("--spin")
    assert result.returncode == 0, result.stdout + result.stderr + robot.logs()
    verdicts = verdict_lines(result.stdout)
    for check in ("configuration", "GPIO back-end", "pins", "beacon device", "beacon stream", "fix rate",
                  *(f"spin {wheel}" for wheel in WHEELS)):  # fmt: skip
        assert verdicts[check] == "PASS", result.stdout
    # the daemon owns the port: what its status does not carry is skipped, and said why
    assert verdicts["hedgehog"] == verdicts["quality"] == "SKIP"
    assert "robotd is running and owns the serial port" in result.stdout
    assert "robotd is running: nobody may drive it" in result.stdout

    # the daemon still drives after the doctor spun its wheels (its motor outputs were left as it expects them)
    pi: Any = pigpio.pi("127.0.0.1", robot.config.pigpiod.port, show_errors=False)
    link = UdpLink("127.0.0.1", robot.config.teleop.port, None)
    try:
        deadline = time.monotonic() + 10.0
        front_left = robot.config.motors.wheels.front_left
        while pi.read(front_left.in1) != 1 or pi.get_PWM_dutycycle(front_left.enable) == 0:
            assert time.monotonic() < deadline, robot.logs()
            link.send(Twist(0.3, 0.0, 0.0))
            time.sleep(0.05)
    finally:
        link.close()
        stop_pigpio_client(pi)


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_doctor_spin_names_the_wiring_faults_of_a_robot_wired_wrong(robot: VirtualRobot) -> None:
    robot.start_vhw("--swap-encoders", "front_left", "rear_left", "--reverse-motor", "front_right")
    # a person watched: front_right turned backward, the others forward
    result = robot.doctor("--spin", "--seen", "f", "b", "f", "f")
    assert result.returncode == 1, result.stdout + result.stderr + robot.logs()
    out = result.stdout
    assert "FAIL  spin front_left: rear_left encoder reads front_left's wheel" in out
    assert "FAIL  spin rear_left: front_left encoder reads rear_left's wheel" in out
    assert "FAIL  spin front_right: front_right motor reversed" in out
    assert "fix: swap IN1/IN2 (GPIO 21, 26) or set motors.wheels.front_right.sign: -1" in out
    assert "PASS  spin rear_right: forward as you saw" in out
    # robotd is not running here: the doctor reads the beacon's port itself, address included
    assert "PASS  hedgehog: address 7" in out
    assert out.splitlines()[-1] == "robotd doctor: 3 failed, 8 passed, 4 skipped"
