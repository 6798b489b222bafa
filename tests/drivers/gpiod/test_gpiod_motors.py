"""GpiodMotors on a directory laid out as /sys/class/pwm and virtual output lines; the stop paths after a crash."""

from __future__ import annotations

import os
import signal
import textwrap
import time
from dataclasses import dataclass
from pathlib import Path

import pytest
from gpiod_support import stand_in_motors
from process_support import python_child

from drivers.gpiod.lines import GpioUnavailableError
from drivers.gpiod.motors import GpiodMotors, StopReport, stop_gpiod_motors
from drivers.gpiod.pwm import SysfsAttributes, find_pwm_chip
from drivers.virtual.output_lines import VirtualOutputLines
from drivers.virtual.pwm_sysfs import VirtualPwmSysfs


@dataclass(frozen=True)
class Pins:
    enable: int
    in1: int
    in2: int
    sign: int = 1


WHEELS = [Pins(12, 16, 20), Pins(13, 21, 26), Pins(18, 23, 24), Pins(19, 25, 11)]


@dataclass
class Rig:
    sysfs: VirtualPwmSysfs
    lines: VirtualOutputLines

    def motors(self, wheels: list[Pins] = WHEELS, duty_limit: float = 1.0, watchdog: bool = False) -> GpiodMotors:
        return stand_in_motors(wheels, self.sysfs, self.lines, duty_limit=duty_limit, watchdog=watchdog)

    def outputs(self, wheels: list[Pins] = WHEELS) -> list[tuple[float, int, int]]:
        """(enable duty, IN1, IN2) per wheel, as the pins carry them."""
        channel = {12: 0, 13: 1, 18: 2, 19: 3}
        return [
            (self.sysfs.output(channel[w.enable]), self.lines.level(w.in1), self.lines.level(w.in2)) for w in wheels
        ]


@pytest.fixture
def rig(tmp_path: Path) -> Rig:
    journal: list[dict[str, str]] = []
    return Rig(VirtualPwmSysfs(tmp_path, journal=journal), VirtualOutputLines(journal))


def test_duties_set_the_pwm_channels_and_direction_lines(rig: Rig) -> None:
    with rig.motors() as motors:
        assert rig.outputs() == [(0.0, 0, 0)] * 4  # zero from the start
        assert rig.sysfs.exported() == [0, 1, 2, 3]
        assert rig.sysfs.read(rig.sysfs.chip / "pwm0" / "period") == "1000000"  # 1 kHz
        motors.set_duties((0.5, -0.25, 0.0, 1.0))
        assert rig.outputs() == [(0.5, 1, 0), (0.25, 0, 1), (0.0, 0, 0), (1.0, 1, 0)]
        motors.set_duties((-0.5, -0.25, 0.1, 0.0))  # a reversal, an unchanged wheel, a start, a stop
        assert rig.outputs() == [(0.5, 0, 1), (0.25, 0, 1), (0.1, 1, 0), (0.0, 0, 0)]
    assert list((rig.sysfs.root / "class" / "pwm" / "pwmchip0").glob("pwm[0-9]")) == []  # the decoy chip untouched


def test_limit_sign_and_not_a_number(rig: Rig) -> None:
    wheels = [WHEELS[0], Pins(13, 21, 26, -1), WHEELS[2], WHEELS[3]]
    with rig.motors(wheels, duty_limit=0.6) as motors:
        motors.set_duties((0.9, 0.3, -2.0, float("nan")))
        assert rig.outputs(wheels) == [(0.6, 1, 0), (0.3, 0, 1), (0.6, 0, 1), (0.0, 0, 0)]


def test_a_reversal_puts_the_enable_at_zero_before_the_direction_lines_change(rig: Rig) -> None:
    with rig.motors() as motors:
        motors.set_duties((0.5, 0.5, 0.0, 0.0))
        del rig.sysfs.journal[:]
        motors.set_duties((-0.5, 0.5, 0.0, 0.0))
        writes = list(rig.sysfs.journal)
    assert writes[:3] == [{"pwm0/duty_cycle": "0"}, {"gpio16": "0", "gpio20": "1"}, {"pwm0/duty_cycle": "500000"}]


def test_motors_are_zeroed_when_the_program_raises(rig: Rig) -> None:
    def control_loop_that_fails() -> None:
        with rig.motors() as motors:
            motors.set_duties((0.7, 0.7, -0.7, -0.7))
            raise RuntimeError("control loop failed")

    with pytest.raises(RuntimeError, match="control loop failed"):
        control_loop_that_fails()
    assert rig.outputs() == [(0.0, 0, 0)] * 4
    assert rig.sysfs.exported() == []  # disabled and unexported
    assert rig.lines.held == set()


def test_a_failing_write_zeroes_every_motor_before_it_raises(rig: Rig) -> None:
    with rig.motors() as motors:
        motors.set_duties((0.4, 0.4, 0.4, 0.4))
        rig.lines.fail_writes = 1
        with pytest.raises(OSError, match="Input/output error"):
            motors.set_duties((-0.4, 0.4, 0.4, 0.4))
        assert [duty for duty, _, _ in rig.outputs()] == [0.0] * 4


def test_a_channel_left_exported_by_a_crashed_run_is_taken_over(rig: Rig) -> None:
    rig.sysfs.write(rig.sysfs.chip / "export", "2")
    rig.sysfs.write(rig.sysfs.chip / "pwm2" / "period", "50000")
    rig.sysfs.write(rig.sysfs.chip / "pwm2" / "duty_cycle", "40000")
    rig.sysfs.write(rig.sysfs.chip / "pwm2" / "enable", "1")
    with rig.motors() as motors:
        assert rig.outputs()[2] == (0.0, 0, 0)
        motors.set_duties((0.0, 0.0, 0.3, 0.0))
        assert rig.outputs()[2] == (0.3, 1, 0)


def test_writes_refused_while_udev_settles_a_new_channel_are_retried(tmp_path: Path) -> None:
    rig = Rig(VirtualPwmSysfs(tmp_path, settle_writes=3), VirtualOutputLines())
    with rig.motors() as motors:
        motors.set_duties((0.2, 0.2, 0.2, 0.2))
        assert [duty for duty, _, _ in rig.outputs()] == [0.2] * 4


def test_an_enable_pin_without_hardware_pwm_is_refused(rig: Rig) -> None:
    with pytest.raises(ValueError, match="GPIO 17 has no RP1 hardware PWM"):
        rig.motors([Pins(17, 16, 20), *WHEELS[1:]])


def test_no_rp1_pwm_chip_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(GpioUnavailableError, match=r"no PWM chip of device 1f00098000\.pwm.*dtoverlay"):
        stop_gpiod_motors([12, 13, 18, 19], pwm_root=tmp_path)


def test_stop_motors_zeroes_what_a_dead_process_left_through_the_real_sysfs_writes(rig: Rig) -> None:
    abandoned = rig.motors()  # its owner "dies": nothing closes it
    abandoned.set_duties((0.4, -0.4, 0.4, 0.4))
    report = stop_gpiod_motors(
        [12, 13, 18, 19], [16, 20, 21, 26], pwm_root=rig.sysfs.class_root, open_outputs=rig.lines.open
    )  # with the real SysfsAttributes: plain file writes into the directory
    assert [rig.sysfs.output(channel) for channel in range(4)] == [0.0] * 4
    assert [rig.sysfs.read(rig.sysfs.chip / f"pwm{c}" / "duty_cycle") for c in range(4)] == ["0"] * 4
    assert report == StopReport(
        [], "direction pins left as they are: [Errno 16] lines [16, 20, 21, 26] are held by another request"
    )
    abandoned.close()
    report = stop_gpiod_motors([12, 13], [16, 20], pwm_root=rig.sysfs.class_root, open_outputs=rig.lines.open)
    assert report == StopReport([], None)
    assert (rig.lines.level(16), rig.lines.level(20)) == (0, 0)


DRIVER = """
import sys, time
from pathlib import Path
from drivers.gpiod.motors import GpiodMotors
from drivers.gpiod.pwm import find_pwm_chip
from drivers.virtual.output_lines import VirtualOutputLines
from drivers.virtual.pwm_sysfs import VirtualPwmSysfs
from dataclasses import dataclass

@dataclass(frozen=True)
class Pins:
    enable: int
    in1: int
    in2: int
    sign: int = 1

sysfs = VirtualPwmSysfs(Path(sys.argv[1]))
wheels = [Pins(12, 16, 20), Pins(13, 21, 26), Pins(18, 23, 24), Pins(19, 25, 11)]
motors = GpiodMotors(wheels, frequency_hz=1000, duty_limit=1.0, pwm_chip=find_pwm_chip(root=sysfs.class_root),
                     attributes=sysfs, open_outputs=VirtualOutputLines().open, watchdog=True)
motors.set_duties((0.5, 0.5, -0.5, 0.5))
print(motors._watchdog.pid, flush=True)
time.sleep(60)
"""


def test_after_a_sigkill_the_watchdog_process_stops_the_pwm(tmp_path: Path) -> None:
    process = python_child(["-c", textwrap.dedent(DRIVER), str(tmp_path)])
    try:
        assert process.stdout is not None
        watchdog_pid = int(process.stdout.readline())
        chip = find_pwm_chip(root=tmp_path / "class" / "pwm")
        enables = [chip / f"pwm{c}" / "enable" for c in range(4)]
        assert [SysfsAttributes().read(path) for path in enables] == ["1"] * 4
        process.kill()  # SIGKILL: no handler, no finally
        process.wait(20)
        deadline = time.monotonic() + 20  # a generous functional bound, not a timing target
        while any(SysfsAttributes().read(path) != "0" for path in enables) and time.monotonic() < deadline:
            time.sleep(0.02)
        assert [SysfsAttributes().read(path) for path in enables] == ["0"] * 4
        assert [SysfsAttributes().read(chip / f"pwm{c}" / "duty_cycle") for c in range(4)] == ["0"] * 4
        while _alive(watchdog_pid) and time.monotonic() < deadline:
            time.sleep(0.02)
        assert not _alive(watchdog_pid)  # its job done, the watchdog is gone
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
        if process.stdout is not None:
            process.stdout.close()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def test_a_normal_close_ends_the_watchdog(rig: Rig) -> None:
    motors = rig.motors(watchdog=True)
    assert motors._watchdog is not None
    pid = motors._watchdog.pid
    motors.set_duties((0.3, 0.3, 0.3, 0.3))
    motors.close()
    assert not _alive(pid)  # stopped and reaped
    assert rig.sysfs.exported() == []


def test_sigterm_is_ignored_by_the_watchdog(rig: Rig) -> None:
    motors = rig.motors(watchdog=True)
    try:
        assert motors._watchdog is not None
        os.kill(motors._watchdog.pid, signal.SIGTERM)  # systemd's stop reaches every process of the unit
        motors.set_duties((0.3, 0.3, 0.3, 0.3))
        time.sleep(0.2)
        assert _alive(motors._watchdog.pid)
        assert [duty for duty, _, _ in rig.outputs()] == [0.3] * 4  # it waits for its owner to go
    finally:
        motors.close()
