"""The gpiod back-end's deadman (the PWM watchdog process): enables off after the last heartbeat, on the sysfs stand-in.

Added to `robotd bench daemon` (robotd.bench.BENCHMARK_ADDITIONS), beside the pigpio deadman script's figure. The
motors and their deadman are the production ones (drivers.gpiod.motors, drivers.gpiod.deadman, the real watchdog
process) on config/robot.yaml's pins and timing, writing into a directory laid out as /sys/class/pwm
(drivers.virtual.pwm_sysfs); the owner is this process's event loop, bumping the deadman once per control period
as the daemon's control loop does, then hung on purpose while it polls the four duty_cycle files. The figure is the
time from the last heartbeat written to all four duties read as 0 (within one poll, about a millisecond, of the
truth), against deadman_timeout_s plus one control period. Not measured: the sysfs write's way through a real RP1.
"""

from __future__ import annotations

import asyncio
import contextlib
import tempfile
import time
from pathlib import Path

from drivers.gpiod.deadman import GpiodDeadman
from drivers.gpiod.motors import GpiodMotors
from drivers.gpiod.pwm import find_pwm_chip
from drivers.virtual.output_lines import VirtualOutputLines
from drivers.virtual.pwm_sysfs import VirtualPwmSysfs
from drivers.wheels.motors import wheel_pins
from robotd.bench.daemon import percentile
from robotd.config.model import RobotdConfig, load
from robotd.daemon.hardware import deadman_timeout_s

CONFIG = Path(__file__).resolve().parents[2] / "config" / "robot.yaml"
GIVE_UP_S = 5.0


def run(quick: bool) -> dict[str, float]:
    """Hang the owner of driving motors `samples` times; seconds from its last heartbeat to every duty at 0."""
    config = load(str(CONFIG))
    samples = 3 if quick else 20
    with tempfile.TemporaryDirectory(prefix="robotd-bench-") as folder:
        delays = asyncio.run(_measure(config, VirtualPwmSysfs(Path(folder)), samples))
    bound = config.teleop.deadman_timeout_s + 1.0 / config.control.rate_hz
    p50, worst = percentile(delays, 0.5), max(delays)
    print(
        f"gpiod deadman (the PWM watchdog process; its owner hung {samples} times while driving): enables off "
        f"{p50 * 1e3:.0f} ms after the last heartbeat (max {worst * 1e3:.0f} ms); deadman_timeout_s + one control "
        f"period = {bound * 1e3:.0f} ms"
    )
    return {"gpiod_deadman_stop_p50_s": p50, "gpiod_deadman_stop_max_s": worst}


async def _measure(config: RobotdConfig, sysfs: VirtualPwmSysfs, samples: int) -> list[float]:
    period = 1.0 / config.control.rate_hz
    motors = GpiodMotors(
        wheel_pins(config.motors),
        frequency_hz=config.motors.pwm_frequency_hz,
        duty_limit=config.motors.duty_limit,
        pwm_chip=find_pwm_chip(root=sysfs.class_root),
        attributes=sysfs,
        open_outputs=VirtualOutputLines().open,
        heartbeat_timeout_s=deadman_timeout_s(config),
    )
    try:
        assert motors.watchdog is not None
        deadman, trips = GpiodDeadman(motors.watchdog), asyncio.Queue[int]()
        watch = asyncio.create_task(deadman.watch(trips.put_nowait))
        delays = []
        try:
            for _ in range(samples):
                motors.set_duties((0.5, 0.5, 0.5, 0.5))
                for _ in range(round(0.2 / period)):  # driving: one heartbeat a control period
                    deadman.bump()
                    last_heartbeat = time.monotonic()
                    await asyncio.sleep(period)
                delays.append(_hang_until_stopped(sysfs, last_heartbeat))
                await asyncio.wait_for(trips.get(), GIVE_UP_S)  # resumed: the trip is reported
                motors.zero()  # as the daemon does on a trip
        finally:
            deadman.close()
            watch.cancel()
            with contextlib.suppress(asyncio.CancelledError, OSError):
                await watch
        return delays
    finally:
        motors.close()


def _hang_until_stopped(sysfs: VirtualPwmSysfs, last_heartbeat: float) -> float:
    """Block the event loop (no heartbeat) until every channel's duty reads 0; seconds since the last heartbeat."""
    while any(sysfs.output(channel) for channel in range(4)):
        if time.monotonic() - last_heartbeat > GIVE_UP_S:
            raise RuntimeError(f"the PWM watchdog did not stop the motors within {GIVE_UP_S} s")
        time.sleep(0.0005)
    return time.monotonic() - last_heartbeat
