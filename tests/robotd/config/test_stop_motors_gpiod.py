"""`robotd stop-motors` on the gpiod back-end: the RP1 PWM a dead robotd left running is stopped from the config.

The PWM is a directory laid out as /sys/class/pwm (drivers.virtual.pwm_sysfs), named by the file's
`gpio.pwm_class_dir`; the command writes it with the real sysfs writes. There is no GPIO chip on this machine, so the
direction pins are reported as left as they are (with every enable at 0 the L298 coasts whatever they read).
"""

from __future__ import annotations

from pathlib import Path

import pytest
from gpiod_support import stand_in_motors

from drivers.virtual.output_lines import VirtualOutputLines
from drivers.virtual.pwm_sysfs import VirtualPwmSysfs
from drivers.wheels.motors import wheel_pins
from robotd.cli import main
from robotd.config.model import MotorsConfig
from robotd.config.motorpins import read_stop_targets


def config_file(tmp_path: Path, gpio: str) -> str:
    path = tmp_path / "robot.yaml"
    path.write_text(f"gpio: {gpio}\n")
    return str(path)


def test_stop_motors_stops_the_pwm_a_dead_robotd_left_running(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    sysfs = VirtualPwmSysfs(tmp_path / "sys")
    abandoned = stand_in_motors(wheel_pins(MotorsConfig()), sysfs, VirtualOutputLines())
    abandoned.set_duties((0.5, -0.5, 0.5, 0.5))  # then its owner dies: nothing closes it
    assert [sysfs.output(channel) for channel in range(4)] == [0.5] * 4
    status = main(
        ["stop-motors", "--config", config_file(tmp_path, f"{{backend: gpiod, pwm_class_dir: {sysfs.class_root}}}")]
    )
    out, err = capsys.readouterr()
    assert status == 0, err
    assert [sysfs.output(channel) for channel in range(4)] == [0.0] * 4
    assert [sysfs.read(sysfs.chip / f"pwm{c}" / "enable") for c in range(4)] == ["0"] * 4
    assert "every RP1 PWM channel of GPIO 12, 13, 18, 19 stopped" in out
    assert "direction pins left as they are" in err


def test_no_rp1_pwm_chip_exits_69_with_the_fix(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    status = main(["stop-motors", "--config", config_file(tmp_path, f"{{backend: gpiod, pwm_class_dir: {tmp_path}}}")])
    assert status == 69
    assert "no PWM chip of device 1f00098000.pwm" in capsys.readouterr().err


def test_a_broken_gpio_field_falls_back_alone(tmp_path: Path) -> None:
    targets = read_stop_targets(config_file(tmp_path, "{backend: lgpio, pwm_class_dir: /elsewhere/pwm}"))
    assert (targets.gpio.backend, targets.gpio.pwm_class_dir) == ("auto", "/elsewhere/pwm")
    assert targets.fallbacks == (
        "gpio.backend: expected 'pigpio' or 'gpiod' or 'auto', got string 'lgpio'; using 'auto'",
    )
