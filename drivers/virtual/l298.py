"""The L298 bridge rule, checked over a virtual pigpiod's pin history.

An L298 channel has an enable input (PWM) and two direction inputs. Changing a direction input while the enable is
live switches the bridge through a half-changed state (for an instant both low-side or a wrong-way pair conduct
under the motor's current), so a driver must bring the enable to duty 0 before either direction input changes.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from drivers.virtual.pins import PinWrite


@dataclass(frozen=True, slots=True)
class Channel:
    """One L298 channel's GPIOs."""

    enable: int
    in1: int
    in2: int


def bridge_rule_violations(history: Iterable[PinWrite], channels: Iterable[Channel]) -> list[str]:
    """Every write in `history` that changed a direction input while its channel's enable was not at duty 0.

    A pin's state before its first write in the history counts as low and off (an input at reset, pulled down).
    """
    enable_of: dict[int, int] = {}
    for channel in channels:
        enable_of[channel.in1] = enable_of[channel.in2] = channel.enable
    level: dict[int, int] = {}
    duty: dict[int, float] = {}
    violations = []
    for write in history:
        enable = enable_of.get(write.gpio)
        if enable is not None and write.level != level.get(write.gpio, 0) and duty.get(enable, 0.0) != 0.0:
            violations.append(
                f"t={write.t:.6f}: {write.source} {write.command} set GPIO {write.gpio} to {write.level} while "
                f"enable GPIO {enable} was at duty {duty[enable]:.3f}"
            )
        level[write.gpio], duty[write.gpio] = write.level, write.duty
    return violations
