"""The doctor's pin checks: no motor enable on a pin pulled high at boot, no pin held by I2C, SPI or the UART, and
every enable on a PWM pin when the back-end needs one. (Each pin used once is the configuration's own check.)

At reset GPIO 0-8 are pulled up and 9-27 pulled down (Pi 4 and Pi 5): an L298 enable on a pulled-up pin turns its
motor on from power-on until robotd starts. A pin whose function is ALT0..ALT5 belongs to a peripheral; the device
nodes say whether the I2C, SPI and UART drivers are enabled at all (they take the pins back at every boot).
"""

from __future__ import annotations

from pathlib import Path

from robotd.config.model import WHEELS, EncoderPins, MotorPins, RobotdConfig
from robotd.tools.checklist import Finding, failed, passed, skipped

PULLED_UP_AT_BOOT = frozenset(range(9))
BUS_OF_PIN = {
    2: "i2c", 3: "i2c",
    7: "spi", 8: "spi", 9: "spi", 10: "spi", 11: "spi",
    14: "uart", 15: "uart",
}  # fmt: skip
BUS_NAME = {"i2c": "I2C (GPIO 2, 3)", "spi": "SPI0 (GPIO 7-11)", "uart": "the UART (GPIO 14, 15)"}
BUS_DEVICES = {"i2c": ("i2c-1",), "spi": ("spidev0.0", "spidev0.1"), "uart": ("serial0",)}
BUS_FIX = {
    "i2c": "disable I2C (sudo raspi-config nonint do_i2c 1) and reboot",
    "spi": "disable SPI (sudo raspi-config nonint do_spi 1) and reboot",
    "uart": "disable the serial port and its console (sudo raspi-config nonint do_serial_hw 1; do_serial_cons 1)"
    " and reboot",
}


def pins_in_use(config: RobotdConfig) -> list[tuple[str, int]]:
    """Every GPIO the configuration uses, with its dotted path."""
    used: list[tuple[str, int]] = []
    for wheel in WHEELS:
        encoder: EncoderPins = getattr(config.encoders.wheels, wheel)
        motor: MotorPins = getattr(config.motors.wheels, wheel)
        used += [(f"encoders.wheels.{wheel}.a", encoder.a), (f"encoders.wheels.{wheel}.b", encoder.b)]
        used += [(f"motors.wheels.{wheel}.{name}", getattr(motor, name)) for name in ("enable", "in1", "in2")]
    return used


def pin_findings(
    config: RobotdConfig,
    modes: dict[int, str] | None,
    dev: Path,
    pwm_pins: frozenset[int] | None,
    *,
    unknown: str = "the GPIO back-end is not reachable, so the pins' present functions are unknown",
) -> list[Finding]:
    """The pin checks; `modes` (from the back-end) is None when it could not be read (`unknown` says why)."""
    used = pins_in_use(config)
    found: list[Finding] = []
    for path, pin in used:
        if path.endswith(".enable") and pin in PULLED_UP_AT_BOOT:
            found.append(
                failed(
                    "pins",
                    f"{path} is GPIO {pin}, pulled high at boot: the motor runs from power-on until robotd starts",
                    f"move the enable to a GPIO from 9 to 27 (pulled low at boot) and set {path}",
                )
            )
        if pwm_pins is not None and path.endswith(".enable") and pin not in pwm_pins:
            allowed = ", ".join(str(p) for p in sorted(pwm_pins))
            found.append(failed("pins", f"{path} is GPIO {pin}, not a PWM pin", f"use one of GPIO {allowed}"))
    for bus in sorted({BUS_OF_PIN[pin] for _, pin in used if pin in BUS_OF_PIN}):
        users = ", ".join(f"{path} (GPIO {pin})" for path, pin in used if BUS_OF_PIN.get(pin) == bus)
        held = [pin for _, pin in used if BUS_OF_PIN.get(pin) == bus and (modes or {}).get(pin, "").startswith("alt")]
        enabled = [name for name in BUS_DEVICES[bus] if (dev / name).exists()]
        if held or enabled:
            seen = f"GPIO {', '.join(map(str, held))} set to a peripheral function" if held else ""
            seen += f"{'; ' if seen else ''}/dev/{enabled[0]} exists" if enabled else ""
            found.append(failed("pins", f"{BUS_NAME[bus]} is enabled ({seen}) but {users} need the pins", BUS_FIX[bus]))
    if found:
        return found
    names = f"{len(used)} pins, each used once"
    if modes is None:
        return [
            passed("pins", f"{names}; no motor enable pulled high at boot; no bus enabled"),
            skipped("pin functions", unknown),
        ]
    return [passed("pins", f"{names}; no motor enable pulled high at boot; none held by I2C, SPI or the UART")]


OWN_CONSUMERS = ("robotd-encoders", "robotd-motors")
"""The names robotd's line requests give: a running robotd holds its own pins."""


def holder_findings(config: RobotdConfig, holders: dict[int, str | None]) -> list[Finding]:
    """Each configured pin free, or held by the running robotd; one failure per pin another program holds."""
    found: list[Finding] = []
    ours = []
    for path, pin in pins_in_use(config):
        holder = holders.get(pin)
        if holder is None:
            continue
        if holder in OWN_CONSUMERS:
            ours.append(pin)
            continue
        found.append(
            failed(
                "pins free",
                f"{path} is GPIO {pin}, held by {holder or 'a program that gave no name'}",
                f"stop that program (gpioinfo shows who holds each line), or move the wire and set {path}",
            )
        )
    if found:
        return found
    if ours:
        return [passed("pins free", f"no other program holds them; robotd holds {len(ours)} (it is running)")]
    return [passed("pins free", f"none of the {len(holders)} lines is held by another program")]
