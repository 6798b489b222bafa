"""The daemon's deadman keeper in-process, with a fake deadman: trips and losses reported once, the current deadman
replaced cleanly, a failed removal said and not raised."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable

import pytest

from drivers.pigpiod.deadman import DeadmanLostError
from robotd.daemon.deadman_keeper import DeadmanKeeper


class FakeDeadman:
    """A deadman whose watch reports what the test puts in `events`: a trip count, or an error to raise."""

    def __init__(self) -> None:
        self.bumps = 0
        self.closed = False
        self.uninstalled = False
        self.events: asyncio.Queue[int | OSError] = asyncio.Queue()
        self.uninstall_error: OSError | None = None

    def bump(self) -> None:
        self.bumps += 1

    async def watch(self, on_trip: Callable[[int], None]) -> None:
        while True:
            event = await self.events.get()
            if isinstance(event, OSError):
                raise event
            on_trip(event)

    async def uninstall(self) -> None:
        if self.uninstall_error is not None:
            raise self.uninstall_error
        self.uninstalled = True

    def close(self) -> None:
        self.closed = True
        self.events.put_nowait(ConnectionResetError("closed"))  # as a closed socket ends the real watch


class Harness:
    """A keeper whose factory makes fake deadmen, and what it reported."""

    def __init__(self) -> None:
        self.made: list[FakeDeadman] = []
        self.trips: list[int] = []
        self.lost: list[OSError] = []
        self.keeper = DeadmanKeeper(
            self.make, on_trip=self.trips.append, on_lost=self.lost.append, uninstall_timeout_s=1.0
        )

    async def make(self) -> FakeDeadman:
        self.made.append(FakeDeadman())
        return self.made[-1]


async def settle() -> None:
    for _ in range(5):
        await asyncio.sleep(0)


async def test_trips_are_reported_and_a_loss_drops_the_deadman_once() -> None:
    harness = Harness()
    keeper = harness.keeper
    follower = asyncio.create_task(keeper.follow())
    await keeper.install()
    keeper.bump()
    keeper.bump()
    deadman = harness.made[0]
    assert deadman.bumps == 2
    deadman.events.put_nowait(1)
    await settle()
    assert harness.trips == [1]
    deadman.events.put_nowait(DeadmanLostError("the deadman script is halted"))
    await settle()
    assert [str(error) for error in harness.lost] == ["the deadman script is halted"]
    assert keeper.current is None
    assert deadman.closed
    keeper.bump()  # nothing to bump until the motors come back
    assert deadman.bumps == 2
    follower.cancel()


async def test_a_new_deadman_replaces_the_old_one_whose_end_is_not_a_loss() -> None:
    harness = Harness()
    keeper = harness.keeper
    follower = asyncio.create_task(keeper.follow())
    await keeper.install()
    await settle()
    await keeper.install()  # a reconnection
    await settle()
    old, new = harness.made
    assert old.closed
    assert harness.lost == [], "replacing the deadman on purpose was reported as a loss"
    new.events.put_nowait(3)
    await settle()
    assert harness.trips == [3], "the new deadman is not followed"
    follower.cancel()


async def test_uninstall_removes_the_deadman_and_a_failure_is_logged_not_raised(
    caplog: pytest.LogCaptureFixture,
) -> None:
    harness = Harness()
    await harness.keeper.install()
    await harness.keeper.uninstall()
    assert harness.made[0].uninstalled
    await harness.keeper.install()
    harness.made[1].uninstall_error = ConnectionRefusedError("pigpiod is gone")
    with caplog.at_level(logging.WARNING, logger="robotd"):
        await harness.keeper.uninstall()
    assert "could not remove the deadman script from pigpiod (pigpiod is gone)" in caplog.text
    assert harness.keeper.current is None


async def test_without_a_factory_the_keeper_does_nothing() -> None:
    keeper = DeadmanKeeper(None, on_trip=lambda _t: None, on_lost=lambda _e: None, uninstall_timeout_s=1)
    await keeper.install()
    keeper.bump()
    await keeper.uninstall()
    assert keeper.current is None


async def test_the_heartbeat_is_passed_on_at_its_own_pace_whatever_the_control_rate() -> None:
    now = [0.0]
    made: list[FakeDeadman] = []

    async def make() -> FakeDeadman:
        made.append(FakeDeadman())
        return made[-1]

    keeper = DeadmanKeeper(
        make, on_trip=lambda _t: None, on_lost=lambda _e: None, uninstall_timeout_s=1.0, heartbeat_s=0.125,
        clock=lambda: now[0],
    )  # fmt: skip
    await keeper.install()
    for step in range(50):  # one second of a 50 Hz control loop
        now[0] = step * 0.02
        keeper.bump()
    # a heartbeat at least every 0.125 s (the deadman trips only a timeout after the last), far fewer than steps
    assert 8 <= made[0].bumps <= 11
    now[0] += 0.001
    await keeper.install()  # a reconnection: the new deadman hears the next bump at once
    keeper.bump()
    assert made[1].bumps == 1
