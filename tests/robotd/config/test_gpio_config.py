"""The `gpio` section: the back-end by name or by board, and the gpiod back-end's pins checked by dotted path."""

from __future__ import annotations

from pathlib import Path

import pytest

from robotd.config.gpio import GpioConfig, resolve_backend
from robotd.config.model import parse
from robotd.config.schema import ConfigError
from robotd.daemon import preflight

PI5 = b"Raspberry Pi 5 Model B Rev 1.0\0"
PI4 = b"Raspberry Pi 4 Model B Rev 1.4\0"


def root_with_model(tmp_path: Path, model: bytes | None) -> Path:
    if model is not None:
        path = tmp_path / "proc" / "device-tree" / "model"
        path.parent.mkdir(parents=True)
        path.write_bytes(model)
    return tmp_path


@pytest.mark.parametrize(
    ("backend", "model", "resolved"),
    [
        ("auto", PI5, "gpiod"),
        ("auto", PI4, "pigpio"),
        ("auto", None, "pigpio"),  # no device tree: not a Pi (the virtual robot)
        ("pigpio", PI5, "pigpio"),  # named: the board is not asked
        ("gpiod", PI4, "gpiod"),
    ],
)
def test_the_back_end_by_name_or_by_board(tmp_path: Path, backend: str, model: bytes | None, resolved: str) -> None:
    gpio = parse(f"gpio: {{backend: {backend}}}").gpio
    assert resolve_backend(gpio, root_with_model(tmp_path, model)) == resolved


def test_the_shipped_configurations_choose_by_board_and_the_virtual_robot_pigpio() -> None:
    repo = Path(__file__).resolve().parents[3]
    assert parse((repo / "config" / "robot.yaml").read_text()).gpio.backend == "auto"
    assert parse((repo / "config" / "sim.yaml").read_text()).gpio.backend == "pigpio"
    assert GpioConfig().backend == "auto"


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("gpio: {backend: lgpio}", "gpio.backend: expected 'pigpio' or 'gpiod' or 'auto', got string 'lgpio'"),
        ("gpio: {pwm_class_dir: sys/class/pwm}", "gpio.pwm_class_dir: must be an absolute path, got 'sys/class/pwm'"),
        ("gpio: {event_buffer_size: 4096}", "gpio.event_buffer_size: "),
        (
            "gpio: {backend: gpiod}\nmotors: {wheels: {rear_right: {enable: 9}}}",
            (
                "motors.wheels.rear_right.enable: the gpiod back-end needs an RP1 hardware PWM pin (12, 13, 18, 19), "
                "got GPIO 9"
            ),
        ),
    ],
)
def test_a_bad_gpio_setting_is_named_by_its_dotted_path(text: str, problem: str) -> None:
    with pytest.raises(ConfigError) as error:
        parse(text)
    assert any(line.startswith(problem) for line in error.value.problems), error.value.problems


def test_auto_checks_the_enable_pins_at_start_only_where_it_resolves_to_gpiod(monkeypatch: pytest.MonkeyPatch) -> None:
    config = parse(
        "gpio: {backend: auto}\nmotors: {wheels: {rear_right: {enable: 9}}}\n"
        "teleop: {bind: 127.0.0.1, key_file: '', allow_unauthenticated: true}"
    )
    preflight.preflight(config)  # this machine is no Pi 5: pigpio drives any pin
    monkeypatch.setattr(preflight, "resolve_backend", lambda _gpio: "gpiod")
    with pytest.raises(ConfigError, match=r"motors\.wheels\.rear_right\.enable: the gpiod back-end needs"):
        preflight.preflight(config)
