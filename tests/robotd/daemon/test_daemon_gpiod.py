"""The daemon on the gpiod back-end (Raspberry Pi 5), built from its configuration by robotd.daemon.hardware.

The wheels are the Pi 5 stand-ins: kernel edge-event records through a pipe (drivers.virtual.event_pipe), a directory
laid out as /sys/class/pwm named by the configuration's `gpio.pwm_class_dir` (drivers.virtual.pwm_sysfs) and
recording output lines. Teleop arrives over real UDP on loopback.
"""

from __future__ import annotations

import asyncio
import os
import signal
import time
from dataclasses import dataclass, replace
from pathlib import Path

import pytest
from gpiod_support import drive_turns
from inprocess_daemon import daemon_config, running, until

from drivers.gpiod.motors import GpiodMotors
from drivers.gpiod.pwm import RP1_PWM_CHANNELS
from drivers.settings import in_wheel_order
from drivers.virtual.event_pipe import VirtualEventLines
from drivers.virtual.output_lines import VirtualOutputLines
from drivers.virtual.pwm_sysfs import VirtualPwmSysfs
from drivers.wheels.encoders import wiring
from robotd.config.model import RobotdConfig
from robotd.daemon.hardware import GpiodIo, build_hardware
from robotd.daemon.service import Daemon
from robotd.kinematics import Twist
from robotd.tools.teleop_client import UdpLink

Outputs = list[tuple[float, int, int]]


@dataclass
class Pi5:
    """The stand-ins of a Pi 5's GPIO, and the configuration that names them."""

    config: RobotdConfig
    edges: VirtualEventLines
    lines: VirtualOutputLines
    sysfs: VirtualPwmSysfs

    @property
    def io(self) -> GpiodIo:
        return GpiodIo(self.edges.open, self.lines.open, self.sysfs)

    def outputs(self) -> Outputs:
        """(enable duty, IN1, IN2) per wheel, as the pins carry them."""
        pins = in_wheel_order(self.config.motors.wheels)
        return [
            (self.sysfs.output(RP1_PWM_CHANNELS[p.enable]), self.lines.level(p.in1), self.lines.level(p.in2))
            for p in pins
        ]


@pytest.fixture
def pi5(tmp_path: Path) -> Pi5:
    sysfs = VirtualPwmSysfs(tmp_path / "sys")
    config = daemon_config(
        tmp_path,
        gpio={"backend": "gpiod", "pwm_class_dir": str(sysfs.class_root), "pwm_watchdog": False},
        control={"rate_hz": 50},
    )
    return Pi5(config, VirtualEventLines(), VirtualOutputLines(), sysfs)


def test_the_configured_back_end_is_built_and_auto_follows_the_board(pi5: Pi5, tmp_path: Path) -> None:
    gpiod = build_hardware(pi5.config, time.monotonic, gpiod_io=pi5.io)
    assert (gpiod.backend, type(gpiod.encoders).__name__, gpiod.deadman_factory) == ("gpiod", "GpiodEncoders", None)
    auto = daemon_config(tmp_path, gpio={"backend": "auto"})
    model = tmp_path / "root" / "proc" / "device-tree" / "model"
    model.parent.mkdir(parents=True)
    model.write_bytes(b"Raspberry Pi 5 Model B Rev 1.0\0")
    assert build_hardware(auto, time.monotonic, root=tmp_path / "root").backend == "gpiod"
    model.write_bytes(b"Raspberry Pi 4 Model B Rev 1.4\0")
    pigpio = build_hardware(auto, time.monotonic, root=tmp_path / "root")
    assert (pigpio.backend, type(pigpio.encoders).__name__) == ("pigpio", "PigpioEncoders")
    assert pigpio.deadman_factory is not None  # pigpiod's deadman script, as motors.deadman_script asks


async def test_the_daemon_drives_and_counts_on_the_gpiod_back_end_and_stops_the_pwm_on_the_way_out(pi5: Pi5) -> None:
    daemon = Daemon(pi5.config, hardware=build_hardware(pi5.config, time.monotonic, gpiod_io=pi5.io))
    link = UdpLink("127.0.0.1", pi5.config.teleop.port, None)
    async with running(daemon) as task:
        await until(lambda: daemon.motors is not None, "the motors connected")
        assert pi5.outputs() == [(0.0, 0, 0)] * 4  # zero from the start
        assert await asyncio.to_thread(link.sync, 5.0), "the daemon answered the teleop hello"

        async def forward() -> bool:
            link.send(Twist(0.2, 0.0, 0.0))
            await asyncio.sleep(0.02)
            return all(duty > 0 and (in1, in2) == (1, 0) for duty, in1, in2 in pi5.outputs())

        async with asyncio.timeout(10):
            while not await forward():
                pass
        # Every wheel turns half a revolution forward, a twentieth at a time as a turning wheel delivers its edges
        # (the pipe, like the kernel's buffer, holds about a thousand): they come back as kernel records.
        encoders = wiring(pi5.config.encoders)
        start_ns, parts = time.monotonic_ns(), 20
        for part in range(parts):
            before, after = [0.5 * part / parts] * 4, [0.5 * (part + 1) / parts] * 4
            ends = drive_turns(pi5.edges, encoders, after, start_ns + part * 2_500_000, 2_500_000, 6800, before)
            decoded = sum(ends)
            await until(lambda: daemon.encoders.counters.reports == decoded, "the edges decoded")  # noqa: B023
        try:
            await until(lambda: daemon.estimator.pose().x > 0.14, "the odometry moving the pose forward half a turn")
        except AssertionError as error:  # seen once under a CPU hog, not reproduced: say what the filter had
            seen = daemon._status_message(daemon.clock())
            wheels = {key: seen["filter"][key] for key in ("wheels", "dropped_out_of_order", "dropped_non_finite")}
            counts = seen["drivers"]["encoders"]
            feed = daemon.estimator._wheels  # what the filter holds: the sample that ended the last step, the newest
            held = f"feed base {feed.base} at {feed.base_t}, last {feed.last} at {feed.last_t}, {feed.pending()}"
            ticks = f"ticks decoded {getattr(daemon.encoders, 'ticks', None)} at {daemon.clock()}"
            pose = daemon.estimator.pose()
            raise AssertionError(f"{error}: pose {pose}, {wheels}, {counts}, {held}, {ticks}") from error
        status = daemon._status_message(daemon.clock())["drivers"]["encoders"]
        assert status["reports"] == sum(ends) == 4 * 3400
        assert (status["lost_reports"], status["state"]) == (0, "ok")
        task.cancel()
    link.sock.close()
    assert pi5.outputs() == [(0.0, 0, 0)] * 4
    assert pi5.sysfs.exported() == []  # disabled and unexported
    assert pi5.lines.held == set()
    assert [request for request, _ in pi5.edges.requests] == [sorted(line for e in encoders for line in (e.a, e.b))]


def test_with_the_pwm_watchdog_the_gpiod_back_end_has_a_heartbeat_deadman(pi5: Pi5) -> None:
    config = replace(pi5.config, gpio=replace(pi5.config.gpio, pwm_watchdog=True))
    assert build_hardware(config, time.monotonic, gpiod_io=pi5.io).deadman_factory is not None
    off = replace(config, motors=replace(config.motors, deadman_script=False))
    assert build_hardware(off, time.monotonic, gpiod_io=pi5.io).deadman_factory is None  # death guarded only


async def test_a_hung_loop_has_its_pwm_zeroed_by_the_watchdog_and_drives_again_only_on_a_fresh_command(
    pi5: Pi5, caplog: pytest.LogCaptureFixture
) -> None:
    config = replace(
        pi5.config,
        gpio=replace(pi5.config.gpio, pwm_watchdog=True),
        teleop=replace(pi5.config.teleop, deadman_timeout_s=0.3),
    )
    daemon = Daemon(config, hardware=build_hardware(config, time.monotonic, gpiod_io=pi5.io))
    link = UdpLink("127.0.0.1", config.teleop.port, None)

    async def driving() -> bool:
        link.send(Twist(0.2, 0.0, 0.0))
        await asyncio.sleep(0.02)
        return all(duty > 0 for duty, _, _ in pi5.outputs())

    def hang_until_the_pwm_is_zero() -> None:  # the event loop blocked: no control period, no heartbeat
        deadline = time.monotonic() + 20.0  # a generous functional bound, not a timing target
        while any(duty for duty, _, _ in pi5.outputs()) and time.monotonic() < deadline:
            time.sleep(0.01)

    async with running(daemon):
        await until(lambda: daemon.deadman.current is not None, "the motors and their deadman")
        assert await asyncio.to_thread(link.sync, 5.0), "the daemon answered the teleop hello"
        async with asyncio.timeout(10):
            while not await driving():
                pass
        hang_until_the_pwm_is_zero()
        assert [duty for duty, _, _ in pi5.outputs()] == [0.0] * 4, "the watchdog did not stop the hung daemon's PWM"
        await until(lambda: "deadman stopped the motors" in caplog.text, "the daemon to hear of the trip")
        await asyncio.sleep(0.2)  # ten periods on the old command: it must not drive again on it
        assert [duty for duty, _, _ in pi5.outputs()] == [0.0] * 4
        async with asyncio.timeout(10):
            while not await driving():  # a fresh command drives, and the heartbeat re-arms the watchdog
                pass
    link.sock.close()
    assert pi5.outputs() == [(0.0, 0, 0)] * 4
    assert pi5.sysfs.exported() == []


async def test_a_killed_watchdog_is_a_lost_deadman_and_the_motors_come_back_with_a_new_one(pi5: Pi5) -> None:
    config = replace(pi5.config, gpio=replace(pi5.config.gpio, pwm_watchdog=True))
    daemon = Daemon(config, hardware=build_hardware(config, time.monotonic, gpiod_io=pi5.io))
    async with running(daemon):
        await until(lambda: daemon.deadman.current is not None, "the motors and their deadman")
        first = daemon.motors
        assert isinstance(first, GpiodMotors)
        assert first.watchdog is not None
        os.kill(first.watchdog.pid, signal.SIGKILL)
        await until(lambda: daemon.motors is not None and daemon.motors is not first, "the motors reconnected")
        assert daemon.deadman.current is not None
        again = daemon.motors
        assert isinstance(again, GpiodMotors)
        assert again.watchdog is not None
        assert again.watchdog.exit_status() is None  # a new watchdog guards them
