"""`robotd vhw`: the virtual robot in real time, behind the same interfaces as the real hardware.

Theory of operation: one asyncio task steps the world every few milliseconds of the monotonic clock. Each step reads
the four L298 channels from the virtual pigpiod (enable PWM duty times the direction inputs, times the wheel's
configured sign), advances the physics with those duties held, through the same timelines as the offline simulator
(truth samples, hedgehog measurements), turns the wheels' true turns into quadrature edges stamped with pigpio ticks
and drives them in one batch, and writes the hedgehog packets that have arrived to the pseudo-terminal as frames,
with the time-shift field set to their real latency at the moment of writing. The stationary beacons' frame goes out
every `sim.beacons_period_s`. Ground truth, the counts the edges encode and the packets as written are recorded as a
sensor log (monotonic clock) for the experiment tools: the daemon never sees it. A packet's record carries the
moment its frame was handed to the pseudo-terminal (the clock read just before the write), for latency measurements;
the log is flushed after every step, so it can be read while the robot runs.

Unplugging the beacon: SIGUSR1 closes the pseudo-terminal's master and removes the link (to the daemon, a USB device
pulled out; packets produced meanwhile are unheard), SIGUSR2 plugs it back in: a new pseudo-terminal linked at the
same configured path, as udev relinks a device that reappears. Each is ignored when already in that state.

Not modelled beyond the offline simulator: edges are driven at the end of the step that produced them (up to one
step late); the duties the daemon sets take effect at the next step, and a step holds the duties it read over all the
time since the one before, so a virtual robot starved by a busy machine drives on with the old duties for as long
as it was starved.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import math
import signal
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

import numpy as np

from drivers.virtual.marvelmind import HedgehogPacket, VirtualMarvelmind, beacons_frame, position_frame
from drivers.virtual.pigpiod import VirtualPigpiod
from drivers.virtual.quadrature_signal import encoder_words, merge_streams
from robotd.config.model import WHEELS, EncoderPins, MotorPins, RobotdConfig
from robotd.logs.sensorlog import LogWriter, Truth, Wheels
from robotd.sim.edges import wheel_edges
from robotd.sim.offline import fix_event, meta_for
from robotd.sim.world import World, build_world

STEP_S = 0.005
"""Period of the live loop: the duties' reaction time and the encoder edges' batching."""


@dataclass(frozen=True, slots=True)
class Miswiring:
    """Wiring faults of the virtual robot, for `robotd doctor` to find (the configuration does not know them)."""

    encoder_of: tuple[int, int, int, int] = (0, 1, 2, 3)
    """For each wheel's encoder pins, the wheel (index) whose turns reach them: swapped cables cross two."""
    motor_sign: tuple[int, int, int, int] = (1, 1, 1, 1)
    """-1 where a motor's leads are swapped: the wheel turns backward when driven forward."""

    @classmethod
    def of(cls, swap_encoders: Sequence[str] = (), reverse_motors: Sequence[str] = ()) -> Miswiring:
        """Faults by wheel name: two wheels whose encoder cables are swapped, and the wheels with reversed motors."""
        encoder_of = list(range(4))
        if swap_encoders:
            first, second = (WHEELS.index(name) for name in swap_encoders)
            encoder_of[first], encoder_of[second] = second, first
        signs = [-1 if name in reverse_motors else 1 for name in WHEELS]
        return cls(
            (encoder_of[0], encoder_of[1], encoder_of[2], encoder_of[3]), (signs[0], signs[1], signs[2], signs[3])
        )

    def describe(self) -> str:
        """The faults in words ('' when wired right)."""
        swapped = [f"{WHEELS[k]} encoder reads {WHEELS[w]}'s wheel" for k, w in enumerate(self.encoder_of) if k != w]
        reversed_motors = [f"{WHEELS[k]} motor reversed" for k, sign in enumerate(self.motor_sign) if sign < 0]
        return ", ".join(swapped + reversed_motors)


class _Recorder:
    """The live run's own sensor log (truth, counts, packets), or nothing."""

    def __init__(self, stream: TextIO | None, writer: LogWriter | None) -> None:
        self._stream, self._writer = stream, writer

    @classmethod
    def open(cls, path: str | None, config: RobotdConfig, seed: int) -> _Recorder:
        if not path:
            return cls(None, None)
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        stream = open(path, "w", encoding="utf-8")  # noqa: SIM115 - closed by close()
        return cls(stream, LogWriter(stream, meta_for(config, f"robotd vhw --seed {seed}")))

    def write(self, event: Truth | Wheels | object) -> None:
        if self._writer is not None:
            self._writer.write(event)  # type: ignore[arg-type]

    def flush(self) -> None:
        if self._stream is not None:
            self._stream.flush()

    def close(self) -> None:
        if self._stream is not None:
            self._stream.close()


class VirtualHardware:
    """The world stepped against a virtual pigpiod and a virtual Marvelmind (see the module docstring)."""

    def __init__(
        self,
        config: RobotdConfig,
        seed: int,
        pigpiod: VirtualPigpiod,
        marvelmind: VirtualMarvelmind,
        start_s: float,
        *,
        clock: Callable[[], float] = time.monotonic,
        miswiring: Miswiring = Miswiring(),
    ) -> None:
        self.config = config
        self.clock = clock
        self.miswiring = miswiring
        self.world: World = build_world(config, seed)
        self.pigpiod = pigpiod
        self.marvelmind = marvelmind
        self.start_s = start_s
        self.motor_pins: list[MotorPins] = [getattr(config.motors.wheels, w) for w in WHEELS]
        self.encoder_pins: list[EncoderPins] = [getattr(config.encoders.wheels, w) for w in WHEELS]
        self.encoder_mask = 0
        for pins in self.encoder_pins:
            self.encoder_mask |= 1 << pins.a | 1 << pins.b
        self.cpr = config.encoders.counts_per_rev
        self.base_tick = pigpiod.tick_at(start_s)  # unwrapped here; masked to 32 bits when driven
        self.now_us = 0
        self.truth_period_us = round(1e6 / config.sim.physics_rate_hz)
        self.next_truth_us = 0
        self.next_beacons_s = 0.0
        self.packets: list[HedgehogPacket] = []
        self.retired: list[VirtualMarvelmind] = []  # pseudo-terminals unplugged so far (for their counters)
        self.records: list[object] = []
        # The encoders' lines start low (position 0 of the Gray cycle), before any client connects.
        pigpiod.drive_levels([self.base_tick & 0xFFFFFFFF], [0], self.encoder_mask)

    def duties(self) -> tuple[float, float, float, float]:
        """The duty each wheel's L298 channel applies now (positive turns the wheel forward)."""
        read = self.pigpiod.pwm_duty
        signs = self.miswiring.motor_sign
        d = [
            read(p.enable) * (read(p.in1) - read(p.in2)) * p.sign * s
            for p, s in zip(self.motor_pins, signs, strict=True)
        ]
        return (d[0], d[1], d[2], d[3])

    def advance(self, until_us: int) -> None:
        """Step the world to `until_us` (microseconds since start) under the present duties, driving the edges."""
        robot, hedgehog = self.world.robot, self.world.hedgehog
        duties = self.duties()
        streams: list[tuple[list[np.ndarray], list[np.ndarray]]] = [([], []) for _ in range(4)]
        while self.now_us < until_us:
            next_us = min(until_us, self.next_truth_us, max(self.now_us + 1, round(hedgehog.next_measurement_s * 1e6)))
            if next_us > self.now_us:
                before = list(robot.wheel_angles)
                robot.step(duties, (next_us - self.now_us) / 1e6)
                for wheel in range(4):
                    ticks, counts = wheel_edges(
                        before[wheel], robot.wheel_angles[wheel], self.now_us, next_us, self.cpr
                    )
                    if len(ticks):
                        streams[wheel][0].append(ticks)
                        streams[wheel][1].append(counts)
                self.now_us = next_us
            now = self.now_us / 1e6
            if round(hedgehog.next_measurement_s * 1e6) <= self.now_us:
                hedgehog.measure(now, *self.world.beacon_xy())
            if self.now_us >= self.next_truth_us:
                self.next_truth_us += self.truth_period_us
                body = robot.body
                self.records.append(Wheels(self.start_s + now, robot.encoder_counts(self.cpr)))
                self.records.append(Truth(self.start_s + now, body.x, body.y, body.theta))
        self._drive(streams)

    def _drive(self, streams: list[tuple[list[np.ndarray], list[np.ndarray]]]) -> None:
        merged = []
        for pins, wheel in zip(self.encoder_pins, self.miswiring.encoder_of, strict=True):
            tick_parts, count_parts = streams[wheel]
            if tick_parts:
                positions = pins.sign * np.concatenate(count_parts)
                words = encoder_words(positions, pins.a, pins.b)
                merged.append((np.concatenate(tick_parts) + self.base_tick, words, 1 << pins.a | 1 << pins.b))
        if merged:
            ticks, words = merge_streams(merged, self.pigpiod_levels())
            self.pigpiod.drive_levels(ticks & 0xFFFFFFFF, words, self.encoder_mask)

    def pigpiod_levels(self) -> int:
        """The encoder pins' present levels, as a bank-1 word."""
        word = 0
        for pins in self.encoder_pins:
            word |= self.pigpiod.level(pins.a) << pins.a | self.pigpiod.level(pins.b) << pins.b
        return word

    def send(self, wall_s: float) -> None:
        """Write the packets that have arrived, and the stationary beacons' frame when due."""
        now = wall_s - self.start_s
        sim = self.config.sim
        if now >= self.next_beacons_s:
            self.next_beacons_s += sim.beacons_period_s
            self.marvelmind.write(beacons_frame(sim.stationary_beacons, self.world.hedgehog.params.frame_code))
        for packet in self.world.hedgehog.due(now):
            shift_ms = min(0xFFFF, round((now - packet.measured_s) * 1000.0))  # its real latency, as written
            sent = dataclasses.replace(packet, arrival_s=wall_s, time_shift_ms=shift_ms)
            frame = position_frame(sent)
            written_s = self.clock()  # the frame enters the pseudo-terminal now: its record's arrival time
            if self.marvelmind.write(frame):
                self.packets.append(sent)
                self.records.append(fix_event(sent, written_s))

    def unplug(self) -> None:
        """Pull the virtual Marvelmind out: close its pseudo-terminal (no-op when already out)."""
        if self.marvelmind.is_open:
            self.retired.append(self.marvelmind)
            self.marvelmind.close()

    def replug(self) -> None:
        """Plug a virtual Marvelmind back in: a new pseudo-terminal at the same link (no-op when plugged in)."""
        if not self.marvelmind.is_open:
            self.marvelmind = VirtualMarvelmind(self.config.marvelmind.device)


async def run_virtual_hardware(
    config: RobotdConfig,
    seed: int,
    *,
    duration_s: float | None = None,
    record_path: str | None = None,
    announce: Callable[[str], None] = print,
    clock: Callable[[], float] = time.monotonic,
    miswiring: Miswiring = Miswiring(),
) -> VirtualHardware:
    """Serve the virtual robot until cancelled, SIGTERM/SIGINT, or duration_s; returns the final state."""
    pigpiod = VirtualPigpiod(config.pigpiod.host, config.pigpiod.port)
    await pigpiod.open()
    marvelmind = VirtualMarvelmind(config.marvelmind.device)
    recorder = _Recorder.open(record_path, config, seed)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    handled = []
    for signum in (signal.SIGTERM, signal.SIGINT):
        with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
            loop.add_signal_handler(signum, stop.set)
            handled.append(signum)
    start = clock()
    hardware = VirtualHardware(config, seed, pigpiod, marvelmind, start, clock=clock, miswiring=miswiring)

    def plug(action: Callable[[], None], what: str) -> None:
        action()
        announce(f"robotd vhw: marvelmind {what}")

    for signum, action, what in (
        (signal.SIGUSR1, hardware.unplug, "unplugged"),
        (signal.SIGUSR2, hardware.replug, "plugged in"),
    ):
        with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
            loop.add_signal_handler(signum, plug, action, what)
            handled.append(signum)
    announce(f"robotd vhw: pigpiod {pigpiod.host}:{pigpiod.port}")
    announce(f"robotd vhw: marvelmind {marvelmind.slave_path} (linked at {config.marvelmind.device})")
    announce(f"robotd vhw: record {record_path or '(none)'}")
    if miswiring.describe():
        announce(f"robotd vhw: wired wrong on purpose: {miswiring.describe()}")
    announce(f"robotd vhw: seed {seed}, running{'' if duration_s is None else f' for {duration_s:g} s'}")
    try:
        deadline = math.inf if duration_s is None else start + duration_s
        next_step = start
        while not stop.is_set():
            now = clock()
            if now >= deadline:
                break
            hardware.advance(round((now - start) * 1e6))
            hardware.send(now)
            if hardware.records:
                for record in hardware.records:
                    recorder.write(record)
                hardware.records.clear()
                recorder.flush()
            next_step = max(next_step + STEP_S, now)
            with contextlib.suppress(TimeoutError):  # asyncio.timeout: 3.11's wait_for can drop a cancellation
                async with asyncio.timeout(max(0.0, next_step - clock())):
                    await stop.wait()
    finally:
        for signum in handled:
            loop.remove_signal_handler(signum)
        recorder.close()
        hardware.marvelmind.close()
        await pigpiod.aclose()
        ptys = [*hardware.retired, hardware.marvelmind]
        announce(
            f"robotd vhw: stopped after {clock() - start:.1f} s; {sum(p.frames_written for p in ptys)} frames "
            f"written, {sum(p.frames_unheard for p in ptys)} unheard; {pigpiod.reports_sent} encoder reports"
        )
    return hardware
