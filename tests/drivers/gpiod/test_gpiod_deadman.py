"""The gpiod back-end's deadman: the real watchdog process on a directory laid out as /sys/class/pwm.

Its timing on a fake clock is pinned by test_gpiod_heartbeat.py; here the real process, pipes and sysfs writes, with
generous functional bounds only: the PWM zeroed when heartbeats stop (an owner SIGSTOPped, in a real process), the
trip reported and re-armed, a disarmed watchdog left alone, a killed watchdog reported lost.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import textwrap
import time
from collections.abc import AsyncIterator, Callable, Iterator
from pathlib import Path

import pytest
from gpiod_support import stand_in_motors
from process_support import python_child

from drivers.gpiod.deadman import GpiodDeadman
from drivers.gpiod.motors import GpiodMotors
from drivers.gpiod.watchdog import lower_direction_pins
from drivers.pigpiod.deadman import DeadmanLostError
from drivers.virtual.output_lines import VirtualOutputLines
from drivers.virtual.pwm_sysfs import VirtualPwmSysfs
from robotd.bench import BENCHMARK_ADDITIONS, gpiod_deadman

BOUND_S = 20.0
"""A generous functional bound, not a timing target (the timing is robotd bench daemon's)."""


class Wheels:
    """Pins of the four wheels: enable on the RP1 PWM, two direction lines."""

    def __init__(self, enable: int, in1: int, in2: int) -> None:
        self.enable, self.in1, self.in2, self.sign = enable, in1, in2, 1


WHEELS = [Wheels(12, 16, 20), Wheels(13, 21, 26), Wheels(18, 23, 24), Wheels(19, 25, 11)]


@contextlib.contextmanager
def guarded_motors(tmp_path: Path, timeout_s: float) -> Iterator[tuple[GpiodMotors, VirtualPwmSysfs]]:
    sysfs = VirtualPwmSysfs(tmp_path)
    motors = stand_in_motors(WHEELS, sysfs, VirtualOutputLines(), watchdog=True, heartbeat_timeout_s=timeout_s)
    try:
        yield motors, sysfs
    finally:
        motors.close()


def duties(sysfs: VirtualPwmSysfs) -> list[float]:
    return [sysfs.output(channel) for channel in range(4)]


async def eventually(condition: Callable[[], bool], what: str) -> None:
    deadline = time.monotonic() + BOUND_S
    while not condition():
        assert time.monotonic() < deadline, f"not within {BOUND_S} s: {what}"
        await asyncio.sleep(0.01)


@contextlib.asynccontextmanager
async def watching(deadman: GpiodDeadman, trips: list[int]) -> AsyncIterator[asyncio.Task[None]]:
    task = asyncio.create_task(deadman.watch(trips.append))
    try:
        yield task
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError, OSError):
            await task


async def bump_for(deadman: GpiodDeadman, seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        deadman.bump()
        await asyncio.sleep(0.02)


async def test_heartbeats_hold_it_off_their_end_zeroes_the_duty_and_the_next_heartbeat_re_arms_it(
    tmp_path: Path,
) -> None:
    with guarded_motors(tmp_path, timeout_s=1.0) as (motors, sysfs):
        assert motors.watchdog is not None
        deadman, trips = GpiodDeadman(motors.watchdog), list[int]()
        async with watching(deadman, trips):
            motors.set_duties((0.5, 0.5, -0.5, 0.5))
            await bump_for(deadman, 0.3)
            assert (duties(sysfs), trips) == ([0.5] * 4, [])  # bumped: no trip
            await eventually(lambda: duties(sysfs) == [0.0] * 4, "the watchdog zeroing the PWM")
            await eventually(lambda: trips == [1], "the trip reported")
            # duty 0 with the channels still enabled, so that the owner can drive again after its trip
            assert [sysfs.read(sysfs.chip / f"pwm{c}" / "enable") for c in range(4)] == ["1"] * 4
            motors.zero()  # what the daemon does on a trip: every pin written again
            motors.set_duties((0.3, 0.3, 0.3, 0.3))
            await bump_for(deadman, 0.1)
            assert duties(sysfs) == [0.3] * 4
            await eventually(lambda: trips == [1, 2], "a second trip: the heartbeat re-armed it")
            assert duties(sysfs) == [0.0] * 4


async def test_an_uninstalled_deadman_no_longer_trips_but_death_is_still_guarded(tmp_path: Path) -> None:
    with guarded_motors(tmp_path, timeout_s=0.1) as (motors, sysfs):
        assert motors.watchdog is not None
        deadman = GpiodDeadman(motors.watchdog)
        deadman.bump()
        motors.set_duties((0.4, 0.4, 0.4, 0.4))
        await deadman.uninstall()
        await asyncio.sleep(0.5)  # five timeouts: a trip could only come late, never early
        assert duties(sysfs) == [0.4] * 4
        assert motors.watchdog.read_reports() == []
    assert duties(sysfs) == [0.0] * 4


async def test_a_killed_watchdog_is_a_lost_deadman(tmp_path: Path) -> None:
    with guarded_motors(tmp_path, timeout_s=1.0) as (motors, _):
        assert motors.watchdog is not None
        deadman = GpiodDeadman(motors.watchdog)
        os.kill(motors.watchdog.pid, signal.SIGKILL)
        with pytest.raises(DeadmanLostError, match="the PWM watchdog process exited"):
            await asyncio.wait_for(deadman.watch(lambda trips: None), BOUND_S)
        deadman.bump()  # a heartbeat to a dead watchdog never raises: the loss is watch()'s to report


async def test_closing_the_deadman_ends_its_watch(tmp_path: Path) -> None:
    with guarded_motors(tmp_path, timeout_s=1.0) as (motors, _):
        assert motors.watchdog is not None
        deadman = GpiodDeadman(motors.watchdog)
        task = asyncio.create_task(deadman.watch(lambda trips: None))
        await asyncio.sleep(0.05)
        deadman.close()
        with pytest.raises(ConnectionAbortedError):
            await asyncio.wait_for(task, BOUND_S)


OWNER = """
import sys, time
from pathlib import Path
from drivers.gpiod.motors import GpiodMotors
from drivers.gpiod.pwm import find_pwm_chip
from drivers.virtual.output_lines import VirtualOutputLines
from drivers.virtual.pwm_sysfs import VirtualPwmSysfs

class Pins:
    def __init__(self, enable, in1, in2):
        self.enable, self.in1, self.in2, self.sign = enable, in1, in2, 1

sysfs = VirtualPwmSysfs(Path(sys.argv[1]))
wheels = [Pins(12, 16, 20), Pins(13, 21, 26), Pins(18, 23, 24), Pins(19, 25, 11)]
motors = GpiodMotors(wheels, frequency_hz=1000, duty_limit=1.0, pwm_chip=find_pwm_chip(root=sysfs.class_root),
                     attributes=sysfs, open_outputs=VirtualOutputLines().open, heartbeat_timeout_s=0.3)
motors.set_duties((0.5, 0.5, -0.5, 0.5))
motors.watchdog.heartbeat()
print("driving", flush=True)
while True:  # a control loop: one heartbeat a period, and what the watchdog reported
    motors.watchdog.heartbeat()
    for trips in motors.watchdog.read_reports() or []:
        print(f"tripped {trips}", flush=True)
    time.sleep(0.02)
"""


def test_a_sigstopped_owner_has_its_pwm_zeroed_and_hears_of_it_when_it_resumes(tmp_path: Path) -> None:
    owner = python_child(["-c", textwrap.dedent(OWNER), str(tmp_path)])
    try:
        assert owner.stdout is not None
        assert owner.stdout.readline() == "driving\n"
        sysfs = VirtualPwmSysfs.existing(tmp_path)  # the owner's stand-in, seen from here
        assert duties(sysfs) == [0.5] * 4
        owner.send_signal(signal.SIGSTOP)  # no handler sees it: only the watchdog can stop the wheels
        deadline = time.monotonic() + BOUND_S
        while duties(sysfs) != [0.0] * 4 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert duties(sysfs) == [0.0] * 4
        owner.send_signal(signal.SIGCONT)
        assert owner.stdout.readline() == "tripped 1\n"
    finally:
        owner.send_signal(signal.SIGCONT)
        owner.kill()
        owner.wait()
        if owner.stdout is not None:
            owner.stdout.close()


def test_direction_pins_are_lowered_when_free_waited_for_while_a_dying_owner_holds_them_and_left_when_held() -> None:
    chip = VirtualOutputLines()
    held = chip.open([16, 20], None)
    held.set_values({16: 1})
    note = lower_direction_pins([16, 20], None, open_outputs=chip.open)
    assert note is not None
    assert note.startswith("direction pins left as they are: [Errno 16]")
    assert chip.level(16) == 1

    def owner_exits(seconds: float) -> None:  # the kernel releases a dead owner's request a moment later
        held.release()

    note = lower_direction_pins([16, 20], None, open_outputs=chip.open, wait_s=BOUND_S, sleep=owner_exits)
    assert (note, chip.level(16), chip.level(20), chip.held) == (None, 0, 0, set())


def test_robotd_bench_daemon_measures_the_gpiod_deadman(capsys: pytest.CaptureFixture[str]) -> None:
    figures = gpiod_deadman.run(quick=True)
    assert "robotd.bench.gpiod_deadman" in BENCHMARK_ADDITIONS["daemon"]  # `robotd bench daemon` runs it
    assert 0 < figures["gpiod_deadman_stop_p50_s"] <= figures["gpiod_deadman_stop_max_s"] < gpiod_deadman.GIVE_UP_S
    assert "enables off" in capsys.readouterr().out
