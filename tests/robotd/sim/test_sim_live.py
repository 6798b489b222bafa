"""`robotd vhw` end to end: the daemon's own drivers and control law drive the virtual robot in real time.

One run of a few seconds, shared by the tests of this module: `robotd vhw` in a subprocess; in this process the
daemon's parts (the encoder source on pigpiod's notification socket, the L298 outputs through gpiozero, the
`MotionController`, a Marvelmind parser on the serial port opened with pyserial-asyncio-fast) drive a short scenario.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import os
import signal
import sys
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import serial_asyncio_fast
from paths import REPO

from drivers.marvelmind.events import FixUnavailable, Position
from drivers.marvelmind.protocol import MarvelmindParser
from drivers.wheels.encoders import PigpioEncoders, WheelTicks
from drivers.wheels.motors import GpiozeroMotors
from robotd.config.model import RobotdConfig, load
from robotd.daemon.control import MotionController
from robotd.kinematics import Twist
from robotd.logs.sensorlog import IpsFix, IpsLost, Truth, Wheels, read_log
from robotd.sim.offline import run
from robotd.sim.scenarios import Scenario, Segment
from robotd.sim.world import geometry_of
from robotd.tools.demo import private_config

SCENARIO = Scenario("live", (Segment(0.3), Segment(2.0, vx=0.3, vy=0.1, wz=0.4), Segment(1.2)))
SEED = 4


@dataclass
class LiveRun:
    """What the daemon's drivers saw, and what the simulator recorded."""

    config: RobotdConfig
    record: Path
    scenario_start: float = 0.0
    final_ticks: tuple[int, ...] = ()
    illegal: tuple[int, ...] = ()
    lost_reports: int = 0
    fixes: list[Position | FixUnavailable] = field(default_factory=list)
    late_s: float = 0.0  # control steps taken later than their period, summed: the live run's timing jitter


def _write_config(tmp: Path) -> Path:
    # The rear-right wheel is wired backwards, encoder and motor both: the daemon's signs must undo it.
    wiring = {
        "encoders": {"wheels": {"rear_right": {"a": 2, "b": 3, "sign": -1}}},
        "motors": {"wheels": {"rear_right": {"enable": 19, "in1": 25, "in2": 11, "sign": -1}}},
    }
    return private_config(REPO / "config" / "sim.yaml", tmp, wiring)


async def _drive(live: LiveRun) -> None:
    """The daemon's side: encoders, control law and motors through the scenario, and the Marvelmind port."""
    config = live.config
    latest: list[WheelTicks] = []
    encoders = PigpioEncoders(config.encoders, config.pigpiod)
    parser = MarvelmindParser()
    loop = asyncio.get_running_loop()
    async with asyncio.TaskGroup() as tasks:
        encoder_task = tasks.create_task(encoders.run(latest.append))
        reader, writer = await serial_asyncio_fast.open_serial_connection(url=config.marvelmind.device)

        async def read_fixes() -> None:
            while data := await reader.read(4096):
                events = parser.feed(data, loop.time())
                live.fixes += [e for e in events if isinstance(e, Position | FixUnavailable)]

        fix_task = tasks.create_task(read_fixes())
        motors = await asyncio.to_thread(GpiozeroMotors, config.motors, config.pigpiod)
        controller = MotionController(geometry_of(config), config.control, config.teleop, config.motors.duty_limit)
        try:
            while not latest:
                await asyncio.sleep(0.01)
            start = live.scenario_start = loop.time()
            command, command_time = Twist(0.0, 0.0, 0.0), start
            next_command = start
            now = start
            while now < start + SCENARIO.duration_s:
                if now >= next_command:  # the remote control's 10 Hz
                    command, command_time = Twist(*SCENARIO.command_at(now - start)), now
                    next_command += 1.0 / config.sim.teleop_rate_hz
                motors.set_duties(controller.step(now, command, command_time, latest[-1].speeds_rad_s))
                await asyncio.sleep(1.0 / config.control.rate_hz)
                previous, now = now, loop.time()
                live.late_s += max(0.0, now - previous - 1.0 / config.control.rate_hz - 0.002)
        finally:
            motors.close()
        await asyncio.sleep(0.6)  # the robot coasts to rest and its last edges arrive
        count = len(live.fixes)
        while len(live.fixes) == count:  # close the port just after a frame: nothing is in flight
            await asyncio.sleep(0.002)
        writer.close()
        fix_task.cancel()
        live.final_ticks = encoders.ticks
        live.illegal = encoders.counters.illegal_transitions
        live.lost_reports = encoders.counters.lost_reports
        encoder_task.cancel()


@pytest.fixture(scope="module")
def live_run(tmp_path_factory: pytest.TempPathFactory) -> LiveRun:
    tmp = tmp_path_factory.mktemp("vhw")
    config_path = _write_config(tmp)
    live = LiveRun(load(config_path), tmp / "vhw.jsonl")

    async def main() -> None:
        vhw = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "robotd", "vhw", "--config", str(config_path), "--seed", str(SEED),
            "--record", str(live.record), stdout=asyncio.subprocess.PIPE,
        )  # fmt: skip
        assert vhw.stdout is not None
        try:
            while b"running" not in await asyncio.wait_for(vhw.stdout.readline(), 20.0):
                pass
            await _drive(live)
        finally:
            with contextlib.suppress(ProcessLookupError):
                vhw.send_signal(signal.SIGTERM)
            await asyncio.wait_for(vhw.communicate(), 10.0)
        assert vhw.returncode == 0

    asyncio.run(main())
    return live


@pytest.mark.slow
def test_vhw_prints_its_endpoints_and_links_the_serial_device(live_run: LiveRun) -> None:
    assert not os.path.lexists(live_run.config.marvelmind.device)  # removed when vhw stopped
    assert read_log(live_run.record).meta.source.startswith("robotd vhw")


@pytest.mark.slow
def test_the_daemons_encoder_driver_sees_exactly_the_simulators_ticks(live_run: LiveRun) -> None:
    log = read_log(live_run.record)
    last = [e for e in log.events if isinstance(e, Wheels)][-1]
    assert live_run.illegal == (0, 0, 0, 0)
    assert live_run.lost_reports == 0
    assert min(abs(n) for n in last.ticks) > 1000  # every wheel turned, the reversed one too
    assert live_run.final_ticks == last.ticks


@pytest.mark.slow
def test_the_daemons_marvelmind_parser_sees_exactly_the_simulators_fixes(live_run: LiveRun) -> None:
    log = read_log(live_run.record)
    written = [e for e in log.events if isinstance(e, IpsFix | IpsLost)]
    assert len(written) > 20
    assert len(live_run.fixes) == len(written)
    for seen, sent in zip(live_run.fixes, written, strict=True):
        if isinstance(sent, IpsLost):
            assert isinstance(seen, FixUnavailable)
            continue
        assert isinstance(seen, Position)
        assert (seen.x, seen.y, seen.z) == (sent.x, sent.y, sent.z)
        # the log writes t and t_meas to the microsecond, each rounded on its own: their difference is good to 1 us
        assert seen.time_shift_s == pytest.approx(sent.t - sent.t_meas, abs=1.5e-6)


@pytest.mark.slow
def test_offline_and_live_runs_of_the_same_scenario_and_seed_agree(live_run: LiveRun) -> None:
    live_truth = [e for e in read_log(live_run.record).events if isinstance(e, Truth)]
    offline_truth = [e for e in run(live_run.config, SCENARIO, SEED) if isinstance(e, Truth)]
    offline_at = {round(e.t * 100): e for e in offline_truth}
    gaps = []
    for e in live_truth:
        t = e.t - live_run.scenario_start
        if 0.0 <= t <= SCENARIO.duration_s and round(t * 100) in offline_at:
            o = offline_at[round(t * 100)]
            gaps.append(math.hypot(e.x - o.x, e.y - o.y))
    assert len(gaps) > 200
    final_live, final_offline = live_truth[-1], offline_truth[-1]
    assert math.hypot(final_offline.x, final_offline.y) > 0.5  # the robot went somewhere
    # Live timing jitter (the control loop's sleeps, one 5 ms step of duty latency) shifts the path by millimetres on
    # an idle machine; on a loaded one each late control step holds the old duty for longer, so the bound grows by
    # the distance the robot covers at top speed during the time the steps were late.
    tolerance = 0.02 + 0.5 * live_run.late_s
    assert max(gaps) < tolerance
    assert math.hypot(final_live.x - final_offline.x, final_live.y - final_offline.y) < tolerance
    assert final_live.theta == pytest.approx(final_offline.theta, abs=0.02)
