"""The doctor's checks in-process: pins, key, service, clock, and the whole checklist with a fake back-end.

The key is checked on real files and modes, and the beacon heard through a real pseudo-terminal; the GPIO back-end and
the system tools are fakes here (the real pigpio back-end runs against the virtual pigpiod in test_doctor_live.py).
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import os
import subprocess
import threading
import time
from collections.abc import AsyncIterator, Callable, Sequence
from pathlib import Path

import pytest

from drivers.marvelmind.frames import encode_position_mm
from robotd.cli import main
from robotd.commands.doctor import ask_person
from robotd.config.model import RobotdConfig, parse
from robotd.tools.checklist import Finding, Verdict, exit_status
from robotd.tools.doctor import DoctorOptions, Host, examine
from robotd.tools.doctor_host import clock_finding, key_finding, unit_finding
from robotd.tools.doctor_pins import pin_findings
from robotd.tools.doctor_spin import Seen, SpinPlan
from robotd.tools.gpio_backend import BackendUnavailableError, Counts, GpioBackend

pytestmark = pytest.mark.timeout(30)

# --- pins ------------------------------------------------------------------------------------------------------


def test_the_shipped_wiring_passes_the_pin_checks(tmp_path: Path) -> None:
    modes = dict.fromkeys(range(28), "input")
    [finding] = pin_findings(RobotdConfig(), modes, tmp_path, None)
    assert finding.verdict is Verdict.PASS
    assert "20 pins, each used once" in finding.detail


def test_a_motor_enable_pulled_high_at_boot_fails() -> None:
    config = parse("motors: {wheels: {front_left: {enable: 7, in1: 16, in2: 20}}}\n")
    [finding] = pin_findings(config, {}, Path("/nonexistent"), None)
    assert finding.verdict is Verdict.FAIL
    assert "motors.wheels.front_left.enable is GPIO 7, pulled high at boot" in finding.detail


def test_pins_held_by_an_enabled_bus_fail_with_the_command_that_frees_them(tmp_path: Path) -> None:
    (tmp_path / "i2c-1").touch()
    [finding] = pin_findings(RobotdConfig(), {}, tmp_path, None)
    assert finding.verdict is Verdict.FAIL
    assert "I2C (GPIO 2, 3) is enabled (/dev/i2c-1 exists)" in finding.detail
    assert "encoders.wheels.rear_right.a (GPIO 2)" in finding.detail
    assert "do_i2c 1" in finding.fix
    [finding] = pin_findings(RobotdConfig(), {11: "alt0"}, Path("/nonexistent"), None)
    assert "GPIO 11 set to a peripheral function" in finding.detail
    assert "do_spi 1" in finding.fix


def test_a_back_end_with_pwm_pins_needs_every_enable_on_one() -> None:
    pwm = frozenset({12, 13, 18, 19})
    assert pin_findings(RobotdConfig(), {}, Path("/nonexistent"), pwm)[0].verdict is Verdict.PASS
    config = parse("motors: {wheels: {rear_right: {enable: 10, in1: 25, in2: 11}}}\n")
    [finding] = pin_findings(config, {}, Path("/nonexistent"), pwm)
    assert finding.detail == "motors.wheels.rear_right.enable is GPIO 10, not a PWM pin"


def test_without_the_back_end_the_pin_functions_are_skipped() -> None:
    findings = pin_findings(RobotdConfig(), None, Path("/nonexistent"), None)
    assert [f.verdict for f in findings] == [Verdict.PASS, Verdict.SKIP]


# --- key, service, clock ---------------------------------------------------------------------------------------


def test_the_key_must_be_present_valid_and_private(tmp_path: Path) -> None:
    key = tmp_path / "teleop.key"
    config = parse(f"teleop: {{key_file: {key}}}\n")
    missing = key_finding(config)
    assert missing.verdict is Verdict.FAIL
    assert missing.fix == "sudo robotd install makes a fresh one"
    key.write_text("0123456789abcdef0123456789abcdef\n")
    key.chmod(0o644)
    public = key_finding(config)
    assert public.verdict is Verdict.FAIL
    assert "has mode 0644" in public.detail
    assert public.fix == f"chmod {'0640' if os.geteuid() == 0 else '0600'} {key}"
    key.chmod(0o600)
    assert key_finding(config).verdict is Verdict.PASS
    keyless = parse("teleop: {key_file: '', allow_unauthenticated: true}\n")
    assert key_finding(keyless).verdict is Verdict.SKIP


def tools(answers: dict[str, tuple[int, str]]) -> Callable[[Sequence[str]], subprocess.CompletedProcess[str]]:
    """A fake runner: the first words of a command -> (exit status, output); any other tool is not installed."""

    def run(argv: Sequence[str]) -> subprocess.CompletedProcess[str]:
        line = " ".join(argv)
        for start, (status, out) in answers.items():
            if line.startswith(start):
                return subprocess.CompletedProcess(list(argv), status, out, "")
        return subprocess.CompletedProcess(list(argv), 127, "", "not installed")

    return run


SYSTEMD_OK = {
    "systemctl is-active": (0, "active\n"),
    "systemctl is-enabled": (0, "enabled\n"),
    "systemctl show": (0, "0\n"),
}


def test_the_service_must_be_active_and_not_restarting(tmp_path: Path) -> None:
    running = tmp_path / "run-systemd"
    running.mkdir()
    config = "/etc/robotd/robot.yaml"
    assert unit_finding(config, tools(SYSTEMD_OK), running).verdict is Verdict.PASS
    failed = unit_finding(config, tools(SYSTEMD_OK | {"systemctl is-active": (3, "failed\n")}), running)
    assert (failed.verdict, failed.detail) == (Verdict.FAIL, "robotd.service is failed")
    looping = unit_finding(config, tools(SYSTEMD_OK | {"systemctl show": (0, "4\n")}), running)
    assert "restarted it 4 times" in looping.detail
    absent = unit_finding(config, tools(SYSTEMD_OK | {"systemctl is-enabled": (1, "")}), running)
    assert absent.fix == "sudo robotd install"
    assert unit_finding(config, tools(SYSTEMD_OK), tmp_path / "none").verdict is Verdict.SKIP
    other = unit_finding(str(tmp_path / "sim.yaml"), tools(SYSTEMD_OK), running)
    assert other.verdict is Verdict.SKIP
    assert "runs /etc/robotd/robot.yaml" in other.detail


def test_the_clock_must_be_synchronised() -> None:
    show = "timedatectl show --property=NTPSynchronized --value"
    assert clock_finding(tools({show: (0, "yes\n")})).verdict is Verdict.PASS
    unsynced = clock_finding(tools({show: (0, "no\n")}))
    assert unsynced.verdict is Verdict.FAIL
    assert "teleop.max_clock_offset_s" in unsynced.detail
    no_systemd = {show: (1, ""), "chronyc -n tracking": (0, "Reference ID : 0\nLeap status     : Not synchronised\n")}
    assert clock_finding(tools(no_systemd)).verdict is Verdict.FAIL
    chrony_ok = {"chronyc -n tracking": (0, "Leap status     : Normal\n")}
    assert clock_finding(tools(chrony_ok)).detail == "synchronised (chronyc tracking)"
    assert clock_finding(tools({show: (1, "")})).verdict is Verdict.SKIP


# --- the whole checklist ---------------------------------------------------------------------------------------


class WheelsInTheAir:
    """A fake robot on the real clock: a driven wheel turns at `rate` counts/s; encoders read their own wheels."""

    def __init__(self, rate: float) -> None:
        self.rate = rate
        self.turned = [0.0] * 4
        self.driven: tuple[int, float, float] | None = None  # wheel, duty, since

    def _settle(self) -> None:
        if self.driven is not None:
            wheel, duty, since = self.driven
            now = time.monotonic()
            self.turned[wheel] += (1 if duty > 0 else -1) * self.rate * (now - since)
            self.driven = (wheel, duty, now)

    def drive(self, wheel: int, duty: float) -> None:
        self._settle()
        self.driven = (wheel, duty, time.monotonic())

    def stop(self) -> None:
        self._settle()
        self.driven = None

    def close(self) -> None:
        self.stop()

    def counts(self) -> Counts:
        self._settle()
        return (round(self.turned[0]), round(self.turned[1]), round(self.turned[2]), round(self.turned[3]))


def fake_backend(robot: WheelsInTheAir | None) -> GpioBackend:
    """A back-end answering with `robot`, or unreachable when there is none."""

    def reach(_config: RobotdConfig) -> str:
        if robot is None:
            raise BackendUnavailableError("nothing answers", "start it")
        return "fake GPIO"

    @contextlib.asynccontextmanager
    async def open_counts(_config: RobotdConfig) -> AsyncIterator[Callable[[], Counts]]:
        assert robot is not None
        yield robot.counts

    def open_drive(_config: RobotdConfig) -> WheelsInTheAir:
        assert robot is not None
        return robot

    return GpioBackend("fake", reach, lambda _c, pins: dict.fromkeys(pins, "input"), open_drive, open_counts)


def write_config(tmp_path: Path, device: str, extra: str = "") -> str:
    path = tmp_path / "robot.yaml"
    path.write_text(
        f"marvelmind: {{device: {device}}}\npose_socket: {{path: {tmp_path / 'pose.sock'}}}\n"
        f"teleop: {{key_file: '', allow_unauthenticated: true}}\n{extra}"
    )
    return str(path)


def doctor(tmp_path: Path, config: str, robot: WheelsInTheAir | None, spin: bool) -> list[Finding]:
    host = Host(run=tools({}), dev=tmp_path / "dev", systemd_dir=tmp_path / "no-systemd", backends={})
    host.backends["fake"] = fake_backend(robot)
    plan = SpinPlan(duty=0.5, ramp_s=0.02, measure_s=0.1, coast_s=0.02) if spin else None

    async def watched(_wheel: str) -> Seen:
        return Seen.FORWARD

    options = DoctorOptions(config, backend="fake", beacon_s=0.3, spin=plan, ask=watched)
    return asyncio.run(examine(options, host, lambda _f: None, lambda _text: None))


def test_a_well_wired_robot_passes_the_whole_checklist(tmp_path: Path, beacon_pty: tuple[int, str]) -> None:
    master, device = beacon_pty
    stop = threading.Event()

    def hedgehog() -> None:  # streams while the doctor runs, as a real one does (unheard frames are dropped)
        os.set_blocking(master, False)
        stamp = 0
        while not stop.wait(0.02):
            stamp += 20
            with contextlib.suppress(BlockingIOError):
                os.write(master, encode_position_mm(stamp, 1.0, 2.0, 0.3, 7))

    streaming = threading.Thread(target=hedgehog)
    streaming.start()
    rate = 0.5 * 20.0 / 6.283185307179586 * 6800  # the speed duty 0.5 gives by control.wheel_max_speed_rad_s
    try:
        findings = doctor(tmp_path, write_config(tmp_path, device), WheelsInTheAir(rate), spin=True)
    finally:
        stop.set()
        streaming.join()
    verdicts = {f.check: f.verdict for f in findings}
    assert exit_status(findings) == 0, [f.lines() for f in findings]
    assert [name for name, v in verdicts.items() if v is Verdict.SKIP] == ["quality", "teleop key", "service", "clock"]
    assert all(verdicts[f"spin {wheel}"] is Verdict.PASS for wheel in ("front_left", "rear_right"))


def by_check(findings: list[Finding]) -> dict[str, Finding]:
    return {f.check: f for f in findings}


def test_an_unreachable_back_end_fails_and_the_spin_is_skipped(tmp_path: Path) -> None:
    findings = by_check(doctor(tmp_path, write_config(tmp_path, str(tmp_path / "nothing")), None, spin=True))
    assert findings["GPIO back-end"].verdict is Verdict.FAIL
    assert findings["GPIO back-end"].fix == "start it"
    assert findings["spin"].verdict is Verdict.SKIP
    assert findings["beacon device"].verdict is Verdict.FAIL
    assert exit_status(list(findings.values())) == 1


def test_pins_used_twice_are_named_by_the_configuration_check(tmp_path: Path) -> None:
    config = write_config(tmp_path, "/dev/null", "motors: {wheels: {rear_left: {in1: 16}}}\n")
    findings = doctor(tmp_path, config, None, spin=False)
    assert [f.verdict for f in findings] == [Verdict.FAIL]
    assert findings[0].detail == "motors.wheels.rear_left.in1: GPIO 16 is already used by motors.wheels.front_left.in1"


def test_the_command_exits_1_on_a_failure_and_prints_each_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = write_config(tmp_path, "/dev/null", "motors: {wheels: {rear_left: {in1: 16}}}\n")
    assert main(["doctor", "--config", config]) == 1
    out = capsys.readouterr().out
    assert "FAIL  configuration: motors.wheels.rear_left.in1: GPIO 16 is already used" in out
    assert out.splitlines()[-1] == "robotd doctor: 1 failed, 0 passed, 0 skipped"
    assert main(["doctor", "--config", config, "--spin", "--spin-duty", "3"]) == 2


def test_the_person_is_asked_which_way_each_wheel_turned() -> None:
    prompts = io.StringIO()
    ask = ask_person(io.StringIO("f\n\nB\n"), prompts)

    async def answers() -> list[Seen]:
        return [await ask(wheel) for wheel in ("front_left", "front_right", "rear_left", "rear_right")]

    seen = asyncio.run(answers())
    assert seen == [Seen.FORWARD, Seen.UNSEEN, Seen.BACKWARD, Seen.UNSEEN]  # the last: end of input
    assert prompts.getvalue().startswith("front_left: which way did it turn?")
