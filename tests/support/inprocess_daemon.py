"""The daemon in the test's own process: the real `Daemon` with stand-in wheels, for tests of its logic.

`FakeEncoders` and `FakeMotors` stand in for pigpiod behind the daemon's own seams (`EncoderSource`, `MotorOutputs`).
They do not model pigpiod, gpiozero, edges or decoding: the encoders publish the wheel speeds a test sets (ticks are
their integral), the motors keep every duty they are given. Everything else is the daemon's real code: the teleop
socket on loopback, the pose socket in a temporary folder, the Marvelmind reader on a device that is never plugged in.
Tests either call the daemon's callbacks and control step by hand on a `FakeClock`, or run `Daemon.run()` for real.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import io
import socket
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any, TextIO

import yaml

from drivers.wheels.encoders import EncoderCounters, WheelTicks
from robotd.config.model import RobotdConfig, parse
from robotd.daemon.service import Daemon
from robotd.daemon.teleop import StopCommand, TeleopCommand
from robotd.kinematics import Twist

Duties = tuple[float, float, float, float]
AT_REST: Duties = (0.0, 0.0, 0.0, 0.0)

STOP_TIMEOUT_S = 20.0  # far beyond a daemon's exit (well under a second), well under pytest's timeout


class FakeClock:
    """A monotonic clock moved by hand."""

    def __init__(self, start: float = 100.0) -> None:
        self.now = start

    def __call__(self) -> float:
        return self.now


class FakeEncoders:
    """An encoder source publishing the speeds in `speeds` every `period_s` of real time (see the module docstring)."""

    def __init__(self, clock: Callable[[], float], period_s: float = 0.02) -> None:
        self.clock = clock
        self.period_s = period_s
        self.speeds: list[float] = [0.0, 0.0, 0.0, 0.0]
        self.published = 0
        self.fail_with: BaseException | None = None  # raised by run() at its first publication

    @property
    def counters(self) -> EncoderCounters:
        """Health counters (nothing is ever lost here)."""
        return EncoderCounters(self.published, 0, (0, 0, 0, 0), 0)

    def ticks(self, degraded: bool = False) -> WheelTicks:
        """One publication of the present speeds."""
        a, b, c, d = self.speeds
        return WheelTicks(self.clock(), (0, 0, 0, 0), (a, b, c, d), degraded)

    async def run(self, on_ticks: Callable[[WheelTicks], None]) -> None:
        """Publish until cancelled."""
        while True:
            await asyncio.sleep(self.period_s)
            if self.fail_with is not None:
                raise self.fail_with
            on_ticks(self.ticks())
            self.published += 1


class FakeMotors:
    """Motor outputs that keep every duty written; `fail_next` makes the next write raise as a vanished pigpiod."""

    def __init__(self) -> None:
        self.history: list[Duties] = []
        self.fail_next = False
        self.closed = False

    @property
    def duties(self) -> Duties:
        """The duties now (zero before the first write)."""
        return self.history[-1] if self.history else AT_REST

    def set_duties(self, duties: Duties) -> None:
        """Apply one duty per wheel, or fail once when asked to."""
        if self.fail_next:
            self.fail_next = False
            raise ConnectionResetError("pigpiod closed the connection")
        self.history.append(duties)

    def zero(self) -> None:
        """Stop every motor."""
        self.history.append(AT_REST)

    def close(self) -> None:
        """Zero and release."""
        self.zero()
        self.closed = True


def free_udp_port() -> int:
    """A UDP port on loopback that nobody holds right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port: int = probe.getsockname()[1]
        return port


def daemon_config(folder: Path, **sections: dict[str, Any]) -> RobotdConfig:
    """A valid configuration for a daemon in this process: loopback teleop without a key, paths in `folder`."""
    raw: dict[str, dict[str, Any]] = {
        "teleop": {"bind": "127.0.0.1", "port": free_udp_port(), "key_file": "", "allow_unauthenticated": True},
        "pose_socket": {"path": str(folder / "pose.sock")},
        "marvelmind": {"device": str(folder / "no-beacon")},
    }
    for name, values in sections.items():
        raw.setdefault(name, {}).update(values)
    return parse(yaml.safe_dump(raw))


class Harness:
    """A daemon with fake wheels on a fake clock, its motors connected, driven by hand."""

    def __init__(self, config: RobotdConfig, record: TextIO | None = None) -> None:
        self.clock = FakeClock()
        self.encoders = FakeEncoders(self.clock)
        self.motor_outputs: list[FakeMotors] = []
        self.daemon = Daemon(
            config, record=record, clock=self.clock, encoders=self.encoders, motors_factory=self._new_motors
        )
        self.period_s = self.daemon.controller.period_s
        self._sequence = 0
        self.daemon.motors = self._new_motors()  # as run() connects them at start

    def _new_motors(self) -> FakeMotors:
        motors = FakeMotors()
        self.motor_outputs.append(motors)
        return motors

    @property
    def motors(self) -> FakeMotors:
        """The motor outputs connected last."""
        return self.motor_outputs[-1]

    def send(self, twist: Twist | None) -> None:
        """A valid teleop message arriving now: a command, or a stop for None."""
        self._sequence += 1
        if twist is None:
            self.daemon._on_teleop(StopCommand(1, self._sequence, self.clock.now))
        else:
            self.daemon._on_teleop(TeleopCommand(twist, 1, self._sequence, self.clock.now))

    def tick(self, *, send: Twist | None = None, degraded: bool = False) -> Duties:
        """One control period later: the encoders publish, `send` arrives if given, the control loop steps."""
        self.clock.now += self.period_s
        self.daemon._on_ticks(self.encoders.ticks(degraded))
        if send is not None:
            self.send(send)
        self.daemon._control_step(self.clock.now)
        return self.motors.duties

    def status(self) -> dict[str, Any]:
        """The status message the daemon would publish now."""
        return self.daemon._status_message(self.clock.now)


@contextlib.asynccontextmanager
async def running(daemon: Daemon) -> AsyncIterator[asyncio.Task[int]]:
    """`daemon.run()` as a task of this loop; cancelled on the way out (the motors are zeroed by its finally)."""
    task = asyncio.create_task(daemon.run())
    try:
        yield task
    finally:
        task.cancel()
        # bounded: a daemon that does not end when cancelled is a bug to show (with every task's stack), not a hang
        done, _ = await asyncio.wait({task}, timeout=STOP_TIMEOUT_S)
        gc.unfreeze()  # run() freezes the start-up heap: give the test process its collector back
        if not done:
            stacks = io.StringIO()
            for other in asyncio.all_tasks():
                other.print_stack(limit=6, file=stacks)
            raise AssertionError(
                f"the daemon did not end within {STOP_TIMEOUT_S} s of its cancellation:\n{stacks.getvalue()}"
            )
        with contextlib.suppress(asyncio.CancelledError):
            await task


async def until(condition: Callable[[], bool], what: str, timeout_s: float = 10.0) -> None:
    """Let the loop run until `condition` holds; fail after `timeout_s` (a generous bound, not a timing target)."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout_s
    while not condition():
        if loop.time() > deadline:
            raise AssertionError(f"timed out after {timeout_s:g} s waiting for {what}")
        await asyncio.sleep(0.01)
