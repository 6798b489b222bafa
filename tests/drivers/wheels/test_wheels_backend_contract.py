"""One contract for every GPIO back-end: the pigpio one on the virtual pigpiod, the gpiod one on the Pi 5 stand-ins.

Each rig drives the back-end's hardware side (edges in, pin states out) through its own stand-in; the tests only
speak of wheels: counts after a known edge sequence, direction, lost edges marking the odometry degraded, zero on
close and on a raise, and the bridge rule on a direction change (read from the pins' history, write by write).
"""

from __future__ import annotations

import asyncio
import itertools
import time
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt
import pytest
from gpiod_support import stand_in_motors
from wheels_support import walk

from drivers.gpiod.encoders import GpiodEncoders
from drivers.gpiod.motors import GpiodMotors
from drivers.gpiod.pwm import RP1_PWM_CHANNELS
from drivers.virtual.event_pipe import VirtualEventLines
from drivers.virtual.output_lines import VirtualOutputLines
from drivers.virtual.pigpiod import VirtualPigpiod
from drivers.virtual.pwm_sysfs import VirtualPwmSysfs
from drivers.virtual.quadrature_signal import encoder_words, merge_streams, position_of_state
from drivers.wheels.encoders import PigpioEncoders, WheelTicks, wiring
from drivers.wheels.motors import GpiozeroMotors, MotorOutputs, wheel_pins
from robotd.config.model import EncodersConfig, MotorsConfig, PigpiodConfig

BACKENDS = ["pigpio", "gpiod"]
SIGNS = [1, 1, 1, -1]  # the rear-right encoder is mounted mirrored
MOVES = [
    [1] * 400 + [-1] * 150 + [1] * 3,  # forward, back, forward again
    [-1] * 257,  # backward
    [1, -1] * 60 + [1] * 9,  # dithering then a few steps
    [1] * 1000,
]
WheelState = tuple[float, int, int]
"""(enable duty, IN1, IN2) of one L298 channel."""


# --- encoders ----------------------------------------------------------------------------------------------------


def encoders_config() -> EncodersConfig:
    encoders = EncodersConfig()
    wheels = replace(encoders.wheels, rear_right=replace(encoders.wheels.rear_right, sign=-1))
    return replace(encoders, wheels=wheels, glitch_filter_us=0, publish_rate_hz=100.0)


class EncoderSourceUnderTest(Protocol):
    """What the contract reads from an encoder source besides `run`."""

    @property
    def connected(self) -> bool: ...
    @property
    def ticks(self) -> tuple[int, ...]: ...
    @property
    def counters(self) -> Any: ...
    async def run(self, on_ticks: Callable[[WheelTicks], None]) -> None: ...


@dataclass
class EncoderRig:
    """A back-end's encoder source and the hardware side that feeds it edges."""

    source: EncoderSourceUnderTest
    levels: Callable[[], int]
    """The encoder lines' present levels as a word."""
    drive_levels: Callable[[npt.NDArray[np.int64], npt.NDArray[np.uint32], int], None]
    """Drive level words at times given in microseconds from now."""
    lose: Callable[[int], None]
    published: list[WheelTicks] = field(default_factory=list)

    async def drive(self, moves: list[list[int]], spacing_us: int = 20) -> list[int]:
        """Step each wheel through its +1/-1 moves from its present state, interleaved, a few hundred edges at a
        time as a turning wheel would deliver them (a kernel buffer holds 1024); returns the x4 net moves."""
        streams, mask = [], 0
        levels = self.levels()
        for index, encoder in enumerate(wiring(encoders_config())):
            state = ((levels >> encoder.a) & 1) << 1 | ((levels >> encoder.b) & 1)
            positions = walk(position_of_state(state), moves[index])
            ticks = 1000 + np.arange(len(positions), dtype=np.int64) * spacing_us * 4 + index * spacing_us
            bits = (1 << encoder.a) | (1 << encoder.b)
            streams.append((ticks, encoder_words(positions, encoder.a, encoder.b), bits))
            mask |= bits
        ticks, words = merge_streams(streams, levels)
        for start in range(0, len(ticks), 256):
            self.drive_levels(ticks[start : start + 256], words[start : start + 256], mask)
            await asyncio.sleep(0.002)
        return [sum(m) for m in moves]


@pytest.fixture(params=BACKENDS)
async def encoder_rig(request: pytest.FixtureRequest) -> AsyncIterator[EncoderRig]:
    encoders = encoders_config()
    if request.param == "pigpio":
        async with VirtualPigpiod() as server:

            def drive_pigpio(ticks: npt.NDArray[np.int64], words: npt.NDArray[np.uint32], mask: int) -> None:
                server.drive_levels(((server.tick() + ticks) & 0xFFFFFFFF).astype(np.uint32), words, mask)

            rig = EncoderRig(
                PigpioEncoders(encoders, PigpiodConfig(port=server.port)),
                lambda: sum(server.level(gpio) << gpio for gpio in range(32)),
                drive_pigpio,
                server.lose_reports,
            )
            async with RunningSource(rig):
                yield rig
    else:
        # The encoder lines pulled up, as the pigpio rig's are.
        chip = VirtualEventLines(initial_levels=sum((1 << e.a) | (1 << e.b) for e in wiring(encoders)))

        def drive_gpiod(ticks: npt.NDArray[np.int64], words: npt.NDArray[np.uint32], mask: int) -> None:
            chip.drive_levels(time.monotonic_ns() + ticks * 1000, words, mask)

        source = GpiodEncoders(
            wiring(encoders),
            encoders.counts_per_rev,
            decoding=encoders.decoding,
            publish_rate_hz=encoders.publish_rate_hz,
            open_lines=chip.open,
        )
        rig = EncoderRig(source, lambda: chip.levels, drive_gpiod, chip.lose_events)
        async with RunningSource(rig):
            yield rig


class RunningSource:
    """Runs the rig's source as a task for the test's duration."""

    def __init__(self, rig: EncoderRig) -> None:
        self._rig = rig
        self._task: asyncio.Task[None] | None = None

    async def __aenter__(self) -> None:
        self._task = asyncio.create_task(self._rig.source.run(self._rig.published.append))
        await eventually(lambda: self._rig.source.connected)

    async def __aexit__(self, *_exc: object) -> None:
        assert self._task is not None
        self._task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await self._task


async def eventually(condition: Callable[[], bool], timeout_s: float = 5.0) -> None:
    async with asyncio.timeout(timeout_s):
        while not condition():
            await asyncio.sleep(0.005)


async def test_counts_after_a_known_edge_sequence(encoder_rig: EncoderRig) -> None:
    net = await encoder_rig.drive(MOVES)
    expected = [n * sign for n, sign in zip(net, SIGNS, strict=True)]
    await eventually(lambda: list(encoder_rig.source.ticks) == expected)
    await eventually(lambda: encoder_rig.published[-1].ticks == tuple(expected))
    assert encoder_rig.source.counters.reports == sum(len(m) for m in MOVES)
    assert encoder_rig.source.counters.lost_reports == 0
    assert not encoder_rig.published[-1].degraded


async def test_direction_of_counts_and_speeds(encoder_rig: EncoderRig) -> None:
    seen = len(encoder_rig.published)
    await encoder_rig.drive([[1] * 200, [-1] * 200, [], [1] * 200], spacing_us=50)
    await eventually(lambda: encoder_rig.source.ticks[0] == 200 and encoder_rig.source.ticks[3] == -200)
    await eventually(lambda: len(encoder_rig.published) > seen + 2)
    after = encoder_rig.published[seen:]
    fastest = [max((p.speeds_rad_s[wheel] for p in after), key=abs) for wheel in range(4)]
    assert encoder_rig.source.ticks[:3] == (200, -200, 0)
    assert fastest[0] > 0 > fastest[1]
    assert fastest[2] == 0
    assert fastest[3] < 0  # forward edges on a mirrored encoder


async def test_lost_edges_are_counted_and_mark_the_odometry_degraded(encoder_rig: EncoderRig) -> None:
    await eventually(lambda: len(encoder_rig.published) >= 1)
    assert not encoder_rig.published[-1].degraded
    encoder_rig.lose(3)
    await encoder_rig.drive([[1] * 8, [], [], []])
    await eventually(lambda: encoder_rig.source.counters.reports == 5)
    seen = len(encoder_rig.published)
    await eventually(lambda: len(encoder_rig.published) >= seen + 2)
    assert encoder_rig.source.counters.lost_reports == 3
    assert any(p.degraded for p in encoder_rig.published[seen - 1 :])
    assert not encoder_rig.published[-1].degraded  # the publication that covered the loss, then clear again


# --- motors ------------------------------------------------------------------------------------------------------


@dataclass
class MotorRig:
    """A back-end's motor outputs and the pins' history, one state per hardware write."""

    make: Callable[[], Any]
    """A new motor outputs object (a MotorOutputs and context manager)."""
    outputs: Callable[[], list[WheelState]]
    history: Callable[[], list[list[WheelState]]]
    """The pins' states, one after each hardware write, in order."""


@pytest.fixture(params=BACKENDS)
def motor_rig(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[MotorRig]:
    motors = MotorsConfig()
    pins = wheel_pins(motors)
    if request.param == "pigpio":
        with VirtualPigpiod() as server:
            bank = server._pins  # the virtual Pi's pin state: the recorder runs under the server's lock

            def state() -> list[WheelState]:
                return [(bank.pwm_fraction(p.enable), bank.level(p.in1), bank.level(p.in2)) for p in pins]

            history: list[list[WheelState]] = []
            execute = bank.execute

            def recording(command: Any) -> int:
                result = execute(command)
                history.append(state())
                return result

            bank.execute = recording  # type: ignore[method-assign]
            yield MotorRig(lambda: GpiozeroMotors(motors, PigpiodConfig(port=server.port)), state, history.copy)
    else:
        journal: list[dict[str, str]] = []
        sysfs = VirtualPwmSysfs(tmp_path, journal=journal)
        lines = VirtualOutputLines(journal)

        def outputs() -> list[WheelState]:
            return [(sysfs.output(RP1_PWM_CHANNELS[p.enable]), lines.level(p.in1), lines.level(p.in2)) for p in pins]

        def make() -> GpiodMotors:
            return stand_in_motors(
                pins, sysfs, lines, frequency_hz=motors.pwm_frequency_hz, duty_limit=motors.duty_limit
            )

        yield MotorRig(make, outputs, lambda: _replay(journal, pins))


def _replay(journal: list[dict[str, str]], pins: list[Any]) -> list[list[WheelState]]:
    """The gpiod rig's pin states after each write the stand-ins recorded."""
    pwm: dict[int, dict[str, str]] = {}
    levels: dict[int, int] = {}
    states = []
    for write in journal:
        for key, value in write.items():
            if key.startswith("gpio"):
                levels[int(key[4:])] = int(value)
            elif "/" in key:
                channel, name = key.split("/")
                pwm.setdefault(int(channel[3:]), {})[name] = value
        states.append([_wheel_state(pwm.get(RP1_PWM_CHANNELS[p.enable], {}), levels, p) for p in pins])
    return states


def _wheel_state(channel: dict[str, str], levels: dict[int, int], pins: Any) -> WheelState:
    period = int(channel.get("period", "0"))
    duty = int(channel.get("duty_cycle", "0")) / period if channel.get("enable") == "1" and period else 0.0
    return (duty, levels.get(pins.in1, 0), levels.get(pins.in2, 0))


def settled(rig: MotorRig, expected: list[WheelState], timeout_s: float = 5.0) -> list[WheelState]:
    """The outputs once they equal `expected`, or as they are after `timeout_s`: a back-end may carry out its writes
    after `set_duties` returns (the pigpio one pipelines them to pigpiod without waiting for the answers)."""
    deadline = time.monotonic() + timeout_s
    while (outputs := rig.outputs()) != expected and time.monotonic() < deadline:
        time.sleep(0.005)
    return outputs


def test_duties_reach_the_pins_and_start_from_zero(motor_rig: MotorRig) -> None:
    with motor_rig.make() as motors:
        assert motor_rig.outputs() == [(0.0, 0, 0)] * 4
        motors.set_duties((0.5, -0.25, 0.0, 1.0))
        expected = [(0.5, 1, 0), (0.25, 0, 1), (0.0, 0, 0), (1.0, 1, 0)]
        assert settled(motor_rig, expected) == expected


def test_a_direction_change_never_switches_a_driven_bridge(motor_rig: MotorRig) -> None:
    with motor_rig.make() as motors:
        for duties in [(0.5, -0.5, 0.3, 0.0), (-0.5, 0.5, 0.3, 0.2), (0.6, 0.5, -0.3, -0.2), (0.0, -0.1, 0.3, 0.2)]:
            motors.set_duties(duties)
        expected = [(0.0, 0, 0), (0.1, 0, 1), (0.3, 1, 0), (0.2, 1, 0)]
        assert settled(motor_rig, expected) == expected
    history = motor_rig.history()
    changes = 0
    for before, after in itertools.pairwise(history):
        for wheel in range(4):
            assert after[wheel][1:] != (1, 1), f"wheel {wheel}: both inputs high"
            if before[wheel][1:] != after[wheel][1:]:
                changes += 1
                assert before[wheel][0] == 0.0, f"wheel {wheel}: inputs changed while driven at {before[wheel][0]}"
    assert changes >= 8  # the history really holds the reversals


def test_close_leaves_every_motor_at_zero(motor_rig: MotorRig) -> None:
    motors: MotorOutputs = motor_rig.make()
    motors.set_duties((0.4, -0.4, 0.4, 0.4))
    motors.close()
    assert motor_rig.outputs() == [(0.0, 0, 0)] * 4


def test_a_raise_inside_the_block_leaves_every_motor_at_zero(motor_rig: MotorRig) -> None:
    def control_loop_that_fails() -> None:
        with motor_rig.make() as motors:
            motors.set_duties((0.7, 0.7, -0.7, -0.7))
            expected = [(0.7, 1, 0), (0.7, 1, 0), (0.7, 0, 1), (0.7, 0, 1)]
            assert settled(motor_rig, expected) == expected
            raise RuntimeError("control loop failed")

    with pytest.raises(RuntimeError, match="control loop failed"):
        control_loop_that_fails()
    assert motor_rig.outputs() == [(0.0, 0, 0)] * 4
