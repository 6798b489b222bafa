"""The motor pins and the GPIO back-end, read from a configuration that may be broken (for `robotd stop-motors`).

The last-resort stop must run whatever else is wrong with the file: it reads only `motors.wheels.*.{enable,in1,in2}`,
`pigpiod.{host,port,connect_timeout_s}` and `gpio.{backend,gpio_chip,pwm_class_dir,pwm_device}`, validates each
field on its own, and falls back to the shipped default
for every field it cannot use (the whole file when it cannot be read or parsed), saying which and what it used.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

from robotd.config.gpio import GpioConfig
from robotd.config.model import WHEELS, MotorPins, MotorsConfig, MotorWheels, PigpiodConfig, read_config_text
from robotd.config.schema import ConfigError, build_fields
from robotd.config.yamltext import parse_yaml

PIN_FIELDS = ("enable", "in1", "in2")
PIGPIOD_FIELDS = ("host", "port", "connect_timeout_s")
GPIO_FIELDS = ("backend", "gpio_chip", "pwm_class_dir", "pwm_device")


@dataclass(frozen=True, slots=True)
class StopTargets:
    """What `stop-motors` drives low and where; `fallbacks` says what could not be read and what is used instead."""

    motors: MotorsConfig = field(default_factory=MotorsConfig)
    pigpiod: PigpiodConfig = field(default_factory=PigpiodConfig)
    gpio: GpioConfig = field(default_factory=GpioConfig)
    fallbacks: tuple[str, ...] = ()


def _section(raw: Any, keys: tuple[str, ...], notes: list[str], instead: str) -> Mapping[Any, Any]:
    """The mapping at `keys` inside `raw` ({} when absent), noting where a non-mapping stood in the way."""
    node: Any = raw
    for depth, key in enumerate(keys):
        node = node.get(key) if isinstance(node, Mapping) else None
        if node is None:
            return {}
        if not isinstance(node, Mapping):
            notes.append(f"{'.'.join(keys[: depth + 1])}: expected a mapping, got {type(node).__name__}; {instead}")
            return {}
    return dict(node)


def _defaults_note(motors: MotorsConfig, pigpiod: PigpiodConfig) -> str:
    pins = ", ".join(f"{wheel} {p.enable}/{p.in1}/{p.in2}" for wheel, p in zip(WHEELS, _pins(motors), strict=True))
    return f"using the built-in motor pins (enable/in1/in2: {pins}) and pigpiod {pigpiod.host}:{pigpiod.port}"


def _pins(motors: MotorsConfig) -> list[MotorPins]:
    return [getattr(motors.wheels, wheel) for wheel in WHEELS]


def read_stop_targets(path: str | None) -> StopTargets:
    """The motor pins and pigpiod address of the configuration at `path` (built-in ones when None), never raising."""
    defaults = StopTargets()
    if path is None:
        return defaults
    try:
        raw = parse_yaml(read_config_text(path), path)
    except ConfigError as error:
        return replace(
            defaults, fallbacks=(f"{error.problems[0]}; {_defaults_note(defaults.motors, defaults.pigpiod)}",)
        )
    notes: list[str] = []
    if raw is not None and not isinstance(raw, Mapping):
        notes.append(f"{path}: the top level is not a mapping; {_defaults_note(defaults.motors, defaults.pigpiod)}")
        return replace(defaults, fallbacks=tuple(notes))
    wheels: dict[str, MotorPins] = {}
    for wheel in WHEELS:
        base: MotorPins = getattr(defaults.motors.wheels, wheel)
        instead = f"using the built-in pins of {wheel} ({base.enable}/{base.in1}/{base.in2})"
        section = _section(raw, ("motors", "wheels", wheel), notes, instead)
        wheels[wheel], refused = build_fields(MotorPins, section, f"motors.wheels.{wheel}", base, PIN_FIELDS)
        notes += [f"{problem}; using GPIO {getattr(base, name)}" for name, problem in refused.items()]
    pigpiod_base = defaults.pigpiod
    section = _section(raw, ("pigpiod",), notes, f"using pigpiod {pigpiod_base.host}:{pigpiod_base.port}")
    pigpiod, refused = build_fields(PigpiodConfig, section, "pigpiod", pigpiod_base, PIGPIOD_FIELDS)
    notes += [f"{problem}; using {getattr(pigpiod_base, name)!r}" for name, problem in refused.items()]
    gpio_base = defaults.gpio
    section = _section(raw, ("gpio",), notes, f"using gpio.backend {gpio_base.backend}")
    gpio, refused = build_fields(GpioConfig, section, "gpio", gpio_base, GPIO_FIELDS)
    notes += [f"{problem}; using {getattr(gpio_base, name)!r}" for name, problem in refused.items()]
    motors = replace(defaults.motors, wheels=MotorWheels(**wheels))
    return StopTargets(motors, pigpiod, gpio, tuple(notes))
