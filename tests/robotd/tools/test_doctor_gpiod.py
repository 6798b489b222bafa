"""`robotd doctor` on the gpiod back-end (a Raspberry Pi 5), end to end in-process on the Pi 5 stand-ins.

The checklist runs whole (`examine`, as `robotd doctor --spin` runs it) with the doctor's real gpiod back-end built
on the stand-ins: a directory laid out as /sys/class/pwm, recording output lines, kernel edge records through a pipe,
and the wheels behind them (drivers.virtual.pi5_wheels) turning the PWM duty and direction lines into encoder edges.
Wired right, every GPIO check and every wheel passes; wired wrong, the doctor names the fault.
"""

from __future__ import annotations

import asyncio
import subprocess
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import pytest

from drivers.settings import in_wheel_order
from drivers.virtual.event_pipe import VirtualEventLines
from drivers.virtual.output_lines import VirtualOutputLines
from drivers.virtual.pi5_wheels import VirtualPi5Wheels, WheelWiring
from drivers.virtual.pwm_sysfs import VirtualPwmSysfs
from robotd.config.model import RobotdConfig, load
from robotd.daemon.hardware import GpiodIo
from robotd.tools.checklist import Finding, Verdict
from robotd.tools.doctor import DoctorOptions, Host, examine
from robotd.tools.doctor_gpiod import gpiod_backend
from robotd.tools.doctor_spin import Seen, SpinPlan

pytestmark = pytest.mark.timeout(60)
PLAN = SpinPlan(duty=0.5, ramp_s=0.1, measure_s=0.4, coast_s=0.1)
"""Shorter than a real spin: the stand-in's wheel is at speed at once."""


@dataclass
class Pi5Robot:
    """The stand-ins of a Pi 5's GPIO with four wheels behind them, and the configuration that names them."""

    config_path: str
    config: RobotdConfig
    edges: VirtualEventLines
    lines: VirtualOutputLines
    sysfs: VirtualPwmSysfs
    wheels: VirtualPi5Wheels

    @property
    def io(self) -> GpiodIo:
        return GpiodIo(self.edges.open, self.lines.open, self.sysfs, self.wheels.holders)


MakeRobot = Callable[..., Pi5Robot]


@pytest.fixture
def make_robot(tmp_path: Path) -> Iterator[MakeRobot]:
    made: list[Pi5Robot] = []

    def make(swap_encoders: tuple[int, int] | None = None, reverse_motor: int | None = None) -> Pi5Robot:
        sysfs = VirtualPwmSysfs(tmp_path / f"sys{len(made)}")
        path = tmp_path / f"robot{len(made)}.yaml"
        path.write_text(
            f"gpio: {{backend: gpiod, pwm_class_dir: {sysfs.class_root}, gpio_chip: /dev/gpiochip0}}\n"
            f"marvelmind: {{device: {tmp_path / 'no-beacon'}}}\npose_socket: {{path: {tmp_path / 'pose.sock'}}}\n"
            "teleop: {key_file: '', allow_unauthenticated: true}\n"
        )
        config = load(str(path))
        encoders, motors = in_wheel_order(config.encoders.wheels), in_wheel_order(config.motors.wheels)
        edges, lines = VirtualEventLines(), VirtualOutputLines()
        wheels = VirtualPi5Wheels(
            [WheelWiring(m.enable, m.in1, m.in2, e.a, e.b) for m, e in zip(motors, encoders, strict=True)],
            sysfs=sysfs,
            outputs=lines,
            edges=edges,
            counts_per_rev=config.encoders.counts_per_rev,
            max_speed_rad_s=config.control.wheel_max_speed_rad_s,
            swap_encoders=swap_encoders,
            reverse_motor=reverse_motor,
        )
        made.append(Pi5Robot(str(path), config, edges, lines, sysfs, wheels.start()))
        return made[-1]

    yield make
    for robot in made:
        robot.wheels.stop()


def no_tools(argv: Sequence[str]) -> subprocess.CompletedProcess[str]:
    return subprocess.CompletedProcess(list(argv), 127, "", "not installed")


def doctor(robot: Pi5Robot, tmp_path: Path, *, spin: bool = True, seen: Seen = Seen.UNSEEN) -> dict[str, Finding]:
    host = Host(run=no_tools, dev=tmp_path / "dev", systemd_dir=tmp_path / "no-systemd", backends={})
    host.backends["gpiod"] = gpiod_backend(robot.io)

    async def watched(_wheel: str) -> Seen:
        return seen

    options = DoctorOptions(robot.config_path, beacon_s=0.1, spin=PLAN if spin else None, ask=watched)
    findings = asyncio.run(examine(options, host, lambda _f: None, lambda _text: None))
    return {finding.check: finding for finding in findings}


WHEEL_NAMES = ("front_left", "front_right", "rear_left", "rear_right")


def test_a_well_wired_pi_5_passes_every_gpio_check_and_every_wheel(make_robot: MakeRobot, tmp_path: Path) -> None:
    robot = make_robot()
    found = doctor(robot, tmp_path, seen=Seen.FORWARD)
    assert found["GPIO back-end"].verdict is Verdict.PASS, found["GPIO back-end"].lines()
    assert (
        "gpiod: GPIO chip /dev/gpiochip0 answers for the 20 lines; PWM chip pwmchip2" in found["GPIO back-end"].detail
    )
    assert (found["pins"].verdict, found["pins free"].verdict) == (Verdict.PASS, Verdict.PASS)
    assert found["pin functions"].verdict is Verdict.SKIP
    assert "pinctrl get" in found["pin functions"].detail
    for wheel in WHEEL_NAMES:
        assert found[f"spin {wheel}"].verdict is Verdict.PASS, found[f"spin {wheel}"].lines()
    assert [robot.sysfs.output(channel) for channel in range(4)] == [0.0] * 4  # left stopped
    assert robot.sysfs.exported() == []
    assert robot.lines.held == set()
    assert all(angle > 0.5 for angle in robot.wheels.angles)  # each wheel turned, forward


def test_a_pi_5_wired_wrong_has_its_swapped_encoders_and_reversed_motor_named(
    make_robot: MakeRobot, tmp_path: Path
) -> None:
    robot = make_robot(swap_encoders=(0, 2), reverse_motor=1)
    found = doctor(robot, tmp_path)
    assert found["spin front_left"].verdict is Verdict.FAIL
    assert "swap the encoder cables of front_left and rear_left" in found["spin front_left"].fix
    assert found["spin front_right"].verdict is Verdict.FAIL
    assert "its motor or its encoder is reversed" in found["spin front_right"].detail
    assert found["spin rear_right"].verdict is Verdict.PASS


def test_a_line_held_by_another_program_is_named_and_the_back_end_without_pwm_says_how_to_get_it(
    make_robot: MakeRobot, tmp_path: Path
) -> None:
    robot = make_robot()
    robot.wheels.claimed[robot.config.encoders.wheels.front_left.a] = "gpio-keys"
    found = doctor(robot, tmp_path, spin=False)
    assert found["pins free"].verdict is Verdict.FAIL
    assert found["pins free"].detail.startswith("encoders.wheels.front_left.a is GPIO")
    assert "held by gpio-keys" in found["pins free"].detail
    for chip in robot.sysfs.class_root.iterdir():
        chip.unlink()  # no PWM chip at all: the overlay is missing
    found = doctor(robot, tmp_path)
    assert found["GPIO back-end"].verdict is Verdict.FAIL
    assert "no PWM chip of device 1f00098000.pwm" in found["GPIO back-end"].detail
    assert "robotd[pi5]" in found["GPIO back-end"].fix
    assert found["spin"].verdict is Verdict.SKIP
