"""The deadman script in (virtual) pigpiod: it stops the motor pins when the heartbeat stops, only then, re-arms, is
removed cleanly, reports its loss, and a killed owner's deadman does not fight the next owner of the pins."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from typing import Any

import pigpio
import pytest

from drivers.pigpiod.deadman import (
    SIGNATURE,
    STATUS_S,
    DeadmanLostError,
    PigpioDeadman,
    deadman_script,
    find_deadmen,
    pin_mask,
)
from drivers.pigpiod.protocol import Err
from drivers.virtual.pigpiod import VirtualPigpiod
from drivers.virtual.pins import PinWrite
from drivers.wheels.motors import GpiozeroMotors, enable_and_direction_pins, stop_all_motors
from robotd.config.model import MotorsConfig, PigpiodConfig

MOTORS = MotorsConfig()
ENABLES, DIRECTIONS = enable_and_direction_pins(MOTORS)
PINS = [*ENABLES, *DIRECTIONS]
TIMEOUT_S = 0.3
PERIOD_S = 0.02


def drive(pi: Any) -> None:
    """Every channel forward at half duty, as a motor driver would leave them."""
    for enable, in1 in zip(ENABLES, DIRECTIONS[::2], strict=True):
        pi.write(in1, 1)
        pi.set_PWM_dutycycle(enable, 128)


def all_low(server: VirtualPigpiod) -> bool:
    return all(server.pwm_duty(gpio) == 0.0 and server.level(gpio) == 0 for gpio in PINS)


def script_writes(server: VirtualPigpiod) -> list[PinWrite]:
    return [write for write in server.pin_history() if write.source.startswith("script")]


async def install(server: VirtualPigpiod) -> PigpioDeadman:
    return await PigpioDeadman.install(
        "127.0.0.1", server.port, 2.0, ENABLES, DIRECTIONS, timeout_s=TIMEOUT_S, period_s=PERIOD_S
    )


async def bump_for(deadman: PigpioDeadman, seconds: float) -> float:
    """Bump every period for a while; the time of the last bump."""
    end = time.monotonic() + seconds
    while True:
        deadman.bump()
        last = time.monotonic()
        if last >= end:
            return last
        await asyncio.sleep(PERIOD_S)


async def until(condition: Callable[[], bool], timeout_s: float) -> float:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError("condition not reached in time")
        await asyncio.sleep(0.002)
    return time.monotonic()


def test_the_script_text_stops_enables_before_direction_pins() -> None:
    text = deadman_script([12, 13], [16, 20, 21, 26], slice_ms=20, timeout_ms=500)
    stop = text.split("\n")[-1]
    assert stop == "w 12 0 w 13 0 w 16 0 w 20 0 w 21 0 w 26 0 inr p1 jmp 0"
    with pytest.raises(ValueError, match="GPIO 0-31"):
        pin_mask([40])


async def test_the_pins_go_low_after_the_last_bump_enables_first(server: VirtualPigpiod, pi: Any) -> None:
    drive(pi)
    deadman = await install(server)
    trips: list[int] = []
    watch = asyncio.create_task(deadman.watch(trips.append))
    try:
        last_bump = await bump_for(deadman, 0.6)
        assert not script_writes(server), "the deadman stopped the motors while it was bumped"
        await until(lambda: all_low(server), TIMEOUT_S + 3.0)
        writes = script_writes(server)
        assert [write.gpio for write in writes] == PINS
        assert all(write.mode == 1 and write.level == 0 and write.duty == 0.0 for write in writes)
        # generous functional bounds; the figure itself is `robotd bench daemon`'s
        assert TIMEOUT_S / 2 <= writes[0].t - last_bump <= TIMEOUT_S + 2.0
        assert not trips
        await bump_for(deadman, STATUS_S + 0.2)  # the owner is back: its next status read sees the trip
        await until(lambda: trips == [1], 2.0)
        assert deadman.trips == 1
    finally:
        watch.cancel()
        await deadman.uninstall()


async def test_the_deadman_is_disarmed_until_bumped_and_again_after_a_trip(server: VirtualPigpiod, pi: Any) -> None:
    drive(pi)
    deadman = await install(server)
    watch = asyncio.create_task(deadman.watch(lambda _trips: None))
    try:
        await asyncio.sleep(TIMEOUT_S + 0.3)
        assert not script_writes(server), "a deadman never bumped must not stop anything"
        await bump_for(deadman, 0.1)
        await until(lambda: all_low(server), TIMEOUT_S + 3.0)
        first_trip = len(script_writes(server))
        drive(pi)  # someone else drives the pins after the trip, and the owner is still away
        await asyncio.sleep(TIMEOUT_S + 0.3)
        assert len(script_writes(server)) == first_trip, "the deadman tripped twice on one silence"
        await bump_for(deadman, 0.2)  # the owner is back: armed again
        await until(lambda: all_low(server), TIMEOUT_S + 3.0)
        assert len(script_writes(server)) == 2 * first_trip
        await bump_for(deadman, 0.3)
        await until(lambda: deadman.trips == 2, 2.0)
    finally:
        watch.cancel()
        await deadman.uninstall()


async def test_uninstall_deletes_the_script_and_leaves_the_pins_alone(server: VirtualPigpiod, pi: Any) -> None:
    drive(pi)
    deadman = await install(server)
    await bump_for(deadman, 0.1)
    await deadman.uninstall()
    assert pi.script_status(deadman.script_id)[0] == Err.BAD_SCRIPT_ID
    await asyncio.sleep(TIMEOUT_S + 0.3)
    assert not script_writes(server)
    assert server.pwm_duty(ENABLES[0]) == pytest.approx(128 / 255)


async def test_a_deadman_deleted_behind_its_back_is_reported_lost(server: VirtualPigpiod, pi: Any) -> None:
    deadman = await install(server)
    watch = asyncio.create_task(deadman.watch(lambda _trips: None))
    pi.delete_script(deadman.script_id)
    # the heartbeats' answers are read at each status request, so the refusal is seen while the owner keeps bumping
    bumping = asyncio.create_task(bump_for(deadman, 5.0))
    try:
        with pytest.raises(DeadmanLostError, match="BAD_SCRIPT_ID"):
            await asyncio.wait_for(watch, 5.0)
    finally:
        bumping.cancel()
    deadman.close()


async def test_a_halted_deadman_is_reported_lost(server: VirtualPigpiod, pi: Any) -> None:
    deadman = await install(server)
    watch = asyncio.create_task(deadman.watch(lambda _trips: None))
    pi.stop_script(deadman.script_id)  # someone else halts it: it guards nothing any more
    bumping = asyncio.create_task(bump_for(deadman, 5.0))
    try:
        with pytest.raises(DeadmanLostError, match="halted"):
            await asyncio.wait_for(watch, 10.0)
    finally:
        bumping.cancel()
        await deadman.uninstall()


async def test_a_killed_owners_deadman_is_removed_by_the_next_owner(server: VirtualPigpiod, pi: Any) -> None:
    killed = await install(server)
    await bump_for(killed, 0.1)
    killed.close()  # as SIGKILL leaves it: the script runs on, armed, and nobody will bump it again
    foreign = pi.store_script(b"tag 0 mils 50 jmp 0")
    other_pins = pi.store_script(b"tag 0 mils 50 jmp 0")
    time.sleep(0.05)
    pi.run_script(foreign, [0] * 9 + [SIGNATURE])  # the signature, but another set of pins
    pi.run_script(other_pins, [0] * 8 + [pin_mask([5, 6, 7]), SIGNATURE])
    motors = GpiozeroMotors(MOTORS, PigpiodConfig(port=server.port))
    try:
        assert find_deadmen(pi, PINS) == []
        assert pi.script_status(killed.script_id)[0] == Err.BAD_SCRIPT_ID
        assert pi.script_status(foreign)[0] == pigpio.PI_SCRIPT_RUNNING, "another program's script was removed"
        assert pi.script_status(other_pins)[0] == pigpio.PI_SCRIPT_RUNNING
        motors.set_duties((0.5, 0.5, 0.5, 0.5))
        await asyncio.sleep(TIMEOUT_S + 0.3)
        assert server.pwm_duty(ENABLES[0]) == pytest.approx(0.5, abs=0.01), "the dead owner's deadman stopped us"
    finally:
        motors.close()


async def test_stop_motors_removes_a_killed_owners_deadman(server: VirtualPigpiod, pi: Any) -> None:
    drive(pi)
    killed = await install(server)
    killed.close()
    stop_all_motors(MOTORS, PigpiodConfig(port=server.port))
    assert all_low(server)
    assert find_deadmen(pi, PINS) == []
