"""The `gpio` section: which back-end drives the wheels (pigpio, gpiod, or auto by board), and the gpiod one's paths.

`auto` is resolved once at start (`resolve_backend`): gpiod on an RP1 board (Raspberry Pi 5, 500, CM5: pigpio does not
run there), pigpio everywhere else, including a machine that is no Pi at all (the virtual robot). The gpiod back-end
drives each motor's enable by the RP1's hardware PWM, which exists on four header pins only: `gpiod_problems` names
each enable pin that cannot be one, by its dotted path, when the back-end is (or resolves to) gpiod.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal

from drivers.board import Board, this_board
from drivers.gpiod.pwm import PWM_CLASS, RP1_PWM_CHANNELS, RP1_PWM_DEVICE
from robotd.config.schema import in_range, setting

if TYPE_CHECKING:
    from robotd.config.model import MotorsConfig

Backend = Literal["pigpio", "gpiod"]
WHEELS = ("front_left", "front_right", "rear_left", "rear_right")


def _absolute(value: str) -> str | None:
    """An absolute path."""
    return None if value.startswith("/") else f"must be an absolute path, got {value!r}"


def _device_or_empty(value: str) -> str | None:
    """'' or an absolute path."""
    return None if not value or value.startswith("/") else f"must be '' or an absolute path, got {value!r}"


@dataclass(frozen=True, slots=True)
class GpioConfig:
    """The GPIO back-end: pigpio (through pigpiod, a Pi 4 or earlier) or gpiod (libgpiod and RP1 PWM, a Pi 5)."""

    backend: Literal["pigpio", "gpiod", "auto"] = setting(
        "auto",
        "pigpio, gpiod, or auto: gpiod on a Raspberry Pi 5 (its device-tree model), pigpio elsewhere. The gpiod"
        " back-end needs `pip install 'robotd[pi5]'` and the RP1's PWM on the enable pins (12, 13, 18, 19).",
    )
    gpio_chip: str = setting(
        "",
        "gpiod: the GPIO character device of the encoder and direction lines; '' finds the one labelled"
        " pinctrl-rp1 (its number changed between kernels).",
        _device_or_empty,
    )
    pwm_class_dir: str = setting(PWM_CLASS, "gpiod: where the kernel lists its PWM chips.", _absolute)
    pwm_device: str = setting(
        RP1_PWM_DEVICE, "gpiod: the PWM chip's device name, found by its device path (not its number)."
    )
    event_buffer_size: int = setting(
        1024,
        "gpiod: encoder edges the kernel holds between two reads (it drops the oldest beyond; the loss is counted).",
        in_range(16, 1024),
    )
    pwm_watchdog: bool = setting(
        True,
        "gpiod: run a small watchdog process that stops the PWM when robotd dies without closing (sysfs PWM keeps"
        " running after its process otherwise) and, with motors.deadman_script, when robotd stops refreshing it for"
        " teleop.deadman_timeout_s (stopped or hung): the deadman of the gpiod back-end.",
    )


def resolve_backend(gpio: GpioConfig, root: Path = Path("/")) -> Backend:
    """The back-end to use on the machine whose root directory is `root` (`auto` by its board)."""
    if gpio.backend != "auto":
        return gpio.backend
    return "gpiod" if this_board(root) is Board.PI5 else "pigpio"


def gpiod_problems(motors: MotorsConfig) -> list[str]:
    """Each motor enable pin the gpiod back-end cannot drive (no RP1 hardware PWM on it), by dotted path."""
    problems = []
    for wheel in WHEELS:
        enable = getattr(motors.wheels, wheel).enable
        if enable not in RP1_PWM_CHANNELS:
            problems.append(
                f"motors.wheels.{wheel}.enable: the gpiod back-end needs an RP1 hardware PWM pin"
                f" ({', '.join(map(str, sorted(RP1_PWM_CHANNELS)))}), got GPIO {enable}"
            )
    return problems
