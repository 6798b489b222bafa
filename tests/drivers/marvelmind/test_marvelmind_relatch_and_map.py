"""Under `hedgehog_address: auto` another hedgehog is followed after an outage; fixes outside the map are refused.

Sans-I/O first (the parser, the map bound), then the serial reader on the virtual Marvelmind's real pseudo-terminals:
a hedgehog unplugged and another plugged in at the same link, and a hedgehog that falls silent while another streams.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import AsyncIterator, Callable, Iterator
from pathlib import Path

import pytest

from drivers.marvelmind.events import Event, Position, StationaryBeacon, StationaryBeacons
from drivers.marvelmind.frames import encode_beacons_mm, encode_position_mm
from drivers.marvelmind.mapbound import MapBound
from drivers.marvelmind.protocol import RELATCH_FRAMES, MarvelmindParser
from drivers.marvelmind.reader import MarvelmindReader
from drivers.virtual.marvelmind import VirtualMarvelmind
from robotd.config.model import MarvelmindConfig

BEACONS = (StationaryBeacon(1, 0.0, 0.0, 2.0), StationaryBeacon(2, 5.0, 0.0, 2.0), StationaryBeacon(3, 5.0, 4.0, 2.0))


def fix(address: int, stamp: int, x: float = 1.0, y: float = 1.0) -> bytes:
    return encode_position_mm(stamp, x, y, 0.0, address=address, time_shift_ms=20)


def positions(events: list[Event]) -> list[tuple[int, float]]:
    return [(e.address, e.x) for e in events if isinstance(e, Position)]


# --- the parser --------------------------------------------------------------------------------------------------


def test_auto_follows_another_address_once_ours_is_silent_and_the_other_streams() -> None:
    parser = MarvelmindParser("auto", relatch_after_s=2.0)
    for n in range(5):
        assert positions(parser.feed(fix(5, n), arrival=0.1 * n)) == [(5, 1.0)]
    # hedgehog 5 is gone (last heard at 0.4 s); 7 streams: its frames are dropped until 5 has been silent for 2 s
    seen = [positions(parser.feed(fix(7, 100 + n, x=2.0), arrival=0.5 + 0.25 * n)) for n in range(12)]
    first = next(n for n, got in enumerate(seen) if got)
    assert 0.5 + 0.25 * first >= 0.4 + 2.0
    assert all(got == [(7, 2.0)] for got in seen[first:])
    assert parser.hedgehog_address == 7
    assert parser.previous_address == 5
    assert parser.counters.address_changes == 1
    assert parser.counters.other_address == first
    # and 5 back now is the other hedgehog
    assert positions(parser.feed(fix(5, 50), arrival=4.0)) == []


def test_auto_keeps_its_hedgehog_while_it_streams_beside_another() -> None:
    parser = MarvelmindParser("auto", relatch_after_s=0.5)
    events: list[Event] = []
    for n in range(100):  # 10 s of both, interleaved
        events += parser.feed(fix(5, n) + fix(7, 1000 + n, x=2.0), arrival=0.1 * n)
    assert {address for address, _ in positions(events)} == {5}
    assert parser.counters.address_changes == 0


def test_a_few_stray_frames_of_another_address_do_not_take_over() -> None:
    parser = MarvelmindParser("auto", relatch_after_s=0.5)
    parser.feed(fix(5, 1), arrival=0.0)
    for n in range(RELATCH_FRAMES - 1):
        assert parser.feed(fix(7, 10 + n), arrival=5.0 + n) == []
    assert parser.feed(fix(9, 20), arrival=9.0) == []  # a third address starts its own count
    assert parser.hedgehog_address == 5


def test_a_configured_address_is_never_replaced() -> None:
    parser = MarvelmindParser(5, relatch_after_s=0.1)
    parser.forget_address()
    for n in range(20):
        assert parser.feed(fix(7, n), arrival=float(n)) == []
    assert parser.hedgehog_address == 5


def test_forgetting_the_address_learns_the_next_hedgehogs_even_at_the_same_timestamp() -> None:
    parser = MarvelmindParser("auto")
    parser.feed(fix(5, 42), arrival=0.0)
    parser.forget_address()
    assert positions(parser.feed(fix(7, 42, x=3.0), arrival=0.1)) == [(7, 3.0)]  # another counter: no duplicate
    assert parser.counters.address_changes == 1
    parser.forget_address()
    assert positions(parser.feed(fix(7, 43, x=3.0), arrival=0.2)) == [(7, 3.0)]  # the same one back: no change
    assert parser.counters.address_changes == 1


# --- the map bound -----------------------------------------------------------------------------------------------


def test_the_map_is_the_beacons_box_grown_by_the_margin() -> None:
    bound = MapBound(margin_m=1.0)
    before = bound.box
    assert before is None
    assert bound.admits(1e6, -1e6)  # no map known yet: nothing to hold fixes to
    bound.on_beacons(StationaryBeacons(0.0, (*BEACONS, StationaryBeacon(4, 90.0, 90.0, 2.0, applicable=False)), 0x12))
    assert bound.box == (-1.0, -1.0, 6.0, 5.0)
    assert bound.admits(-1.0, 5.0)
    assert bound.admits(5.9, -0.9)
    assert not bound.admits(6.01, 2.0)
    assert not bound.admits(2.0, -300.0)
    bound.on_beacons(StationaryBeacons(1.0, BEACONS[:1], 0x12))  # one beacon spans no map: the last map stays
    assert bound.box == (-1.0, -1.0, 6.0, 5.0)


def test_configured_bounds_are_used_as_they_are() -> None:
    bound = MapBound((0.0, 0.0, 2.0, 3.0), margin_m=10.0)
    bound.on_beacons(StationaryBeacons(0.0, BEACONS, 0x12))
    assert bound.box == (0.0, 0.0, 2.0, 3.0)
    assert not bound.admits(2.5, 1.0)
    with pytest.raises(ValueError, match="xmin < xmax"):
        MapBound((2.0, 0.0, 0.0, 3.0))


# --- the reader on the virtual Marvelmind --------------------------------------------------------------------------


@pytest.fixture
def link(tmp_path: Path) -> Path:
    return tmp_path / "usb-Marvelmind_Hedgehog-if00"


@pytest.fixture
def hedgehogs() -> Iterator[list[VirtualMarvelmind]]:
    made: list[VirtualMarvelmind] = []
    yield made
    for hedgehog in made:
        hedgehog.close()


@contextlib.asynccontextmanager
async def running(reader: MarvelmindReader) -> AsyncIterator[None]:
    task = asyncio.create_task(reader.run())
    try:
        yield
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


async def stream_until(
    hedgehog: VirtualMarvelmind, frame: Callable[[int], bytes], done: Callable[[], bool], timeout_s: float = 5.0
) -> None:
    """Write frames (numbered from 1) every 20 ms until `done()` (frames nobody reads are dropped, as on USB)."""
    deadline = time.monotonic() + timeout_s
    n = 0
    while not done():
        assert time.monotonic() < deadline, "the reader did not get there in time"
        n += 1
        hedgehog.write(frame(n))
        await asyncio.sleep(0.02)


async def send_once(
    hedgehog: VirtualMarvelmind, frame: bytes, seen: Callable[[], bool], timeout_s: float = 5.0
) -> None:
    """Write one frame to a reader that listens, and wait until `seen()`."""
    assert hedgehog.write(frame)
    deadline = time.monotonic() + timeout_s
    while not seen():
        assert time.monotonic() < deadline, "the reader did not read the frame in time"
        await asyncio.sleep(0.005)


def address_lines(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if "following hedgehog address" in r.getMessage()]


@pytest.mark.timeout(30)
async def test_another_hedgehog_plugged_in_at_the_same_link_is_followed(
    link: Path, hedgehogs: list[VirtualMarvelmind], caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="robotd.marvelmind")
    received: list[Event] = []
    reader = MarvelmindReader(MarvelmindConfig(device=str(link), reconnect_max_s=0.2), received.append)
    hedgehogs.append(VirtualMarvelmind(str(link)))
    async with running(reader):
        await stream_until(hedgehogs[0], lambda n: fix(5, n), lambda: (5, 1.0) in positions(received))
        hedgehogs[0].close()  # unplugged; another hedgehog, with address 7, plugged in where it was
        hedgehogs.append(VirtualMarvelmind(str(link)))
        await stream_until(hedgehogs[1], lambda n: fix(7, n, x=2.0), lambda: (7, 2.0) in positions(received))
    assert reader.counters.address_changes == 1
    assert address_lines(caplog) == [
        "marvelmind: following hedgehog address 5 (auto)",
        "marvelmind: following hedgehog address 7 instead of 5 (auto: the port was reopened)",
    ]


@pytest.mark.timeout(30)
async def test_a_silent_hedgehog_is_replaced_by_the_one_that_streams_on_the_same_port(
    link: Path, hedgehogs: list[VirtualMarvelmind], caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="robotd.marvelmind")
    received: list[Event] = []
    config = MarvelmindConfig(device=str(link), relatch_after_s=0.3)
    reader = MarvelmindReader(config, received.append)
    hedgehogs.append(VirtualMarvelmind(str(link)))
    async with running(reader):
        await stream_until(hedgehogs[0], lambda n: fix(5, n), lambda: (5, 1.0) in positions(received))
        await stream_until(hedgehogs[0], lambda n: fix(7, n, x=2.0), lambda: (7, 2.0) in positions(received))
    assert reader.counters.address_changes == 1
    assert reader.counters.other_address >= RELATCH_FRAMES - 1
    assert address_lines(caplog)[-1] == (
        "marvelmind: following hedgehog address 7 instead of 5 (auto: 5 sent no position for 0.3 s while 7 did)"
    )
    assert reader.health().connected


@pytest.mark.timeout(30)
@pytest.mark.parametrize("bounds", [(), (-1.0, -1.0, 6.0, 5.0)])
async def test_fixes_outside_the_map_are_refused_counted_and_logged_once(
    link: Path, hedgehogs: list[VirtualMarvelmind], caplog: pytest.LogCaptureFixture, bounds: tuple[float, ...]
) -> None:
    caplog.set_level(logging.INFO, logger="robotd.marvelmind")
    received: list[Event] = []
    config = MarvelmindConfig(device=str(link), map_margin_m=1.0, map_bounds_m=bounds)
    reader = MarvelmindReader(config, received.append)
    hedgehogs.append(VirtualMarvelmind(str(link)))
    hedgehog = hedgehogs[0]
    async with running(reader):
        beacons = encode_beacons_mm(BEACONS)
        await stream_until(hedgehog, lambda n: beacons, lambda: reader.counters.frames_by_code.get(0x12, 0) > 0)
        assert reader.map.box == (-1.0, -1.0, 6.0, 5.0)
        xs = [2.0, 300.0, -40.0, 6.5, 2.5, 1e4, 3.0]  # m: the map is x -1..6, y -1..5
        for n, x in enumerate(xs, start=1):  # (each awaited before the next: the lambda sees this n)
            await send_once(hedgehog, fix(5, n, x=x), lambda: reader.counters.frames_by_code.get(0x11, 0) == n)  # noqa: B023
    assert [x for _, x in positions(received)] == [2.0, 2.5, 3.0]
    assert reader.counters.outside_map == 4
    assert reader.counters.as_dict()["outside_map"] == 4  # what the daemon's status carries
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert warnings == [  # the first of each run of refusals
        "marvelmind: fix (300.00, 1.00) m is outside the map x -1.00..6.00, y -1.00..5.00 m: refused",
        "marvelmind: fix (10000.00, 1.00) m is outside the map x -1.00..6.00, y -1.00..5.00 m: refused",
    ]
    back = [r.getMessage() for r in caplog.records if "inside the map again" in r.getMessage()]
    assert back == [
        "marvelmind: fixes inside the map again after 3 refused",
        "marvelmind: fixes inside the map again after 1 refused",
    ]
