"""Four wheels behind the Raspberry Pi 5 stand-ins: the motors' PWM duty and direction lines in, encoder edges out.

Theory of operation: every `step_s` a thread reads each wheel's enable duty from the sysfs stand-in
(drivers.virtual.pwm_sysfs) and its direction inputs from the output lines (drivers.virtual.output_lines), turns the
wheel at duty x `max_speed_rad_s` (IN1 high: forward; IN2 high: backward; both alike: stopped), and drives the
encoder lines of the event-line chip (drivers.virtual.event_pipe) through the quadrature edges of that turn, stamped
on CLOCK_MONOTONIC, with the virtual robot's signal generator (drivers.virtual.quadrature_signal). The edges of a
step are spread evenly over it. Wired wrong on purpose: `swap_encoders` puts two wheels' encoders on each other's
lines, `reverse_motor` turns one wheel backward for a forward command.

`holders` answers line info as drivers.gpiod.lines.read_line_holders does: lines held by the stand-ins' open
requests, under robotd's consumer names, and those a test says another program holds (`claimed`).

Not modelled: the motor's inertia, deadband and load (the wheel is at speed at once), the PWM waveform, the L298's
brake, encoder noise and bounce, and wheels touching the ground.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from drivers.gpiod.lines import LineHolders
from drivers.gpiod.pwm import RP1_PWM_CHANNELS
from drivers.virtual.event_pipe import VirtualEventLines
from drivers.virtual.output_lines import VirtualOutputLines
from drivers.virtual.pwm_sysfs import VirtualPwmSysfs
from drivers.virtual.quadrature_signal import encoder_words, merge_streams


@dataclass(frozen=True, slots=True)
class WheelWiring:
    """One wheel's pins: the motor's enable (an RP1 PWM pin) and direction inputs, the encoder's A and B lines."""

    enable: int
    in1: int
    in2: int
    a: int
    b: int


class VirtualPi5Wheels:
    """The wheels of the module docstring; `start()` runs them, `stop()` (or leaving the `with` block) ends them."""

    def __init__(
        self,
        wheels: Sequence[WheelWiring],
        *,
        sysfs: VirtualPwmSysfs,
        outputs: VirtualOutputLines,
        edges: VirtualEventLines,
        counts_per_rev: int,
        max_speed_rad_s: float,
        step_s: float = 0.005,
        swap_encoders: tuple[int, int] | None = None,
        reverse_motor: int | None = None,
        chip_path: str = "/dev/gpiochip0",
    ) -> None:
        self.wheels = list(wheels)
        self._sysfs, self._outputs, self._edges = sysfs, outputs, edges
        self._scale = counts_per_rev / (2.0 * math.pi)
        self._max_speed = max_speed_rad_s
        self._step_s = step_s
        self._encoder_of = list(range(len(self.wheels)))  # the encoder each wheel turns
        if swap_encoders is not None:
            first, second = swap_encoders
            self._encoder_of[first], self._encoder_of[second] = second, first
        self._motor_sign = [-1.0 if wheel == reverse_motor else 1.0 for wheel in range(len(self.wheels))]
        self.angles = [0.0] * len(self.wheels)
        """Each wheel's true angle, radians, forward positive."""
        self.claimed: dict[int, str] = {}
        """Lines another program holds (line -> its consumer name), for `holders`."""
        self._chip_path = chip_path
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_ns = 0

    def speed(self, wheel: int) -> float:
        """The wheel's speed now, rad/s, from its motor pins."""
        pins = self.wheels[wheel]
        duty = self._sysfs.output(RP1_PWM_CHANNELS[pins.enable])
        direction = self._outputs.level(pins.in1) - self._outputs.level(pins.in2)
        return direction * duty * self._max_speed * self._motor_sign[wheel]

    def step(self, now_ns: int) -> None:
        """Turn the wheels from the last step to `now_ns` (CLOCK_MONOTONIC) and drive their encoders' edges."""
        start_ns, self._last_ns = self._last_ns or now_ns, now_ns
        streams = []
        mask = 0
        for wheel in range(len(self.wheels)):
            before = self.angles[wheel]
            self.angles[wheel] += self.speed(wheel) * (now_ns - start_ns) * 1e-9
            count0, count1 = math.floor(before * self._scale), math.floor(self.angles[wheel] * self._scale)
            encoder = self.wheels[self._encoder_of[wheel]]
            bits = (1 << encoder.a) | (1 << encoder.b)
            mask |= bits
            if count1 == count0:
                continue
            way = 1 if count1 > count0 else -1
            positions = np.arange(count0 + way, count1 + way, way, dtype=np.int64)
            spacing = (now_ns - start_ns) / len(positions)
            stamps = start_ns + np.round(spacing * np.arange(1, len(positions) + 1)).astype(np.int64)
            streams.append((stamps, encoder_words(positions, encoder.a, encoder.b), bits))
        if streams:
            stamps, words = merge_streams(streams, self._edges.levels)
            self._edges.drive_levels(stamps, words, mask)

    def holders(self, offsets: Sequence[int], chip: str | None = None) -> tuple[str, LineHolders]:
        """Who holds each line, as drivers.gpiod.lines.read_line_holders answers (see the module docstring)."""
        encoders = set(self._edges.requested)
        found: LineHolders = {}
        for line in offsets:
            if line in self.claimed:
                found[line] = self.claimed[line]
            elif line in self._outputs.held:
                found[line] = "robotd-motors"
            elif line in encoders:
                found[line] = "robotd-encoders"
            else:
                found[line] = None
        return chip or self._chip_path, found

    def start(self) -> VirtualPi5Wheels:
        """Run the wheels on a thread of their own."""
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="virtual-pi5-wheels", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.wait(self._step_s):
            self.step(time.monotonic_ns())

    def stop(self) -> None:
        """Stop the thread (the wheels keep their angles)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    def __enter__(self) -> VirtualPi5Wheels:
        return self.start()

    def __exit__(self, *exc_info: object) -> None:
        self.stop()
