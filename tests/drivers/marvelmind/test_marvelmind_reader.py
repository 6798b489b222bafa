"""The serial reader on real pseudo-terminals: streaming, never writing, and surviving an unplug."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import pty
import time
import tty
from collections.abc import AsyncIterator, Iterator
from pathlib import Path

import pytest

from drivers.backoff import Backoff
from drivers.marvelmind.events import Event, Position
from drivers.marvelmind.frames import encode_position_mm
from drivers.marvelmind.reader import LinkState, MarvelmindReader, resolve_device
from robotd.config.model import MarvelmindConfig

pytestmark = pytest.mark.timeout(20)


class FakeBeacon:
    """A pseudo-terminal whose slave is linked at `link`, as udev links a hedgehog under /dev/serial/by-id."""

    def __init__(self, link: Path) -> None:
        self.master, self._slave = pty.openpty()
        tty.setraw(self._slave)  # no echo, no line discipline: the bytes pass as on a USB CDC-ACM port
        os.set_blocking(self.master, False)
        temporary = link.with_name(link.name + ".new")
        temporary.symlink_to(os.ttyname(self._slave))
        temporary.replace(link)  # atomic: the reader sees the old device or the new one, never nothing
        self.stamp = 0

    def send_fix(self, x_m: float = 1.0) -> None:
        self.stamp += 10
        os.write(self.master, encode_position_mm(self.stamp, x_m, 2.0, 0.0, address=5, time_shift_ms=20))

    def written_by_reader(self) -> bytes:
        """Whatever the reader wrote to the port (it must write nothing)."""
        try:
            return os.read(self.master, 1024)
        except BlockingIOError:
            return b""

    def unplug(self) -> None:
        """Close both ends: what the host sees when the USB device disappears."""
        os.close(self._slave)
        os.close(self.master)


async def stream_until(beacon: FakeBeacon, received: list[Event], count: int, x_m: float, timeout: float) -> None:
    """Send fixes until `count` positions with this x have arrived (frames sent before the port opened are lost)."""
    deadline = time.monotonic() + timeout
    while sum(1 for e in received if isinstance(e, Position) and e.x == x_m) < count:
        assert time.monotonic() < deadline, "the reader did not stream in time"
        beacon.send_fix(x_m)
        await asyncio.sleep(0.01)


@pytest.fixture
def link(tmp_path: Path) -> Path:
    return tmp_path / "usb-Marvelmind_Hedgehog-if00"


@contextlib.asynccontextmanager
async def running(reader: MarvelmindReader) -> AsyncIterator[asyncio.Task[None]]:
    task = asyncio.create_task(reader.run())
    try:
        yield task
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


@pytest.fixture
def beacons() -> Iterator[list[FakeBeacon]]:
    made: list[FakeBeacon] = []
    yield made
    for beacon in made:
        with contextlib.suppress(OSError):
            beacon.unplug()


async def test_frames_reach_the_callback_and_nothing_is_written(link: Path, beacons: list[FakeBeacon]) -> None:
    beacons.append(FakeBeacon(link))
    received: list[Event] = []
    reader = MarvelmindReader(MarvelmindConfig(device=str(link)), received.append)
    async with running(reader):
        await stream_until(beacons[0], received, 3, 1.0, timeout=3.0)
        health = reader.health()
        assert health.connected
        assert health.state is LinkState.STREAMING
        assert not health.stale
        assert health.device == str(link)
    position = next(e for e in received if isinstance(e, Position))
    assert position.t_meas == pytest.approx(position.arrival - 0.020)
    assert reader.counters.frames_by_code[0x0011] >= 3
    assert beacons[0].written_by_reader() == b""
    assert reader.health(now=time.monotonic() + 1.0).stale


async def test_an_unplugged_device_is_streaming_again_within_a_second(
    link: Path, beacons: list[FakeBeacon], caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="robotd.marvelmind")
    beacons.append(FakeBeacon(link))
    received: list[Event] = []
    reader = MarvelmindReader(MarvelmindConfig(device=str(link), reconnect_max_s=0.5), received.append)
    async with running(reader) as task:
        await stream_until(beacons[0], received, 2, 1.0, timeout=3.0)
        beacons[0].unplug()
        unplugged = time.monotonic()
        while reader.health().connected:  # the reader notices the hang-up
            assert time.monotonic() - unplugged < 1.0
            await asyncio.sleep(0.005)
        await asyncio.sleep(0.15)  # a few failed attempts: each must not be logged again
        beacons.append(FakeBeacon(link))
        await stream_until(beacons[1], received, 1, 3.0, timeout=1.0)
        assert time.monotonic() - unplugged < 1.0 + 0.15
        assert not task.done()
    assert reader.reconnections == 1
    lost = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(lost) == 1, [r.getMessage() for r in lost]
    assert any("streaming from" in r.getMessage() and "after" in r.getMessage() for r in caplog.records)


async def test_a_missing_device_is_waited_for_and_found_by_glob(tmp_path: Path, beacons: list[FakeBeacon]) -> None:
    received: list[Event] = []
    pattern = str(tmp_path / "usb-Marvelmind*")
    reader = MarvelmindReader(MarvelmindConfig(device=pattern, reconnect_max_s=0.1), received.append)
    async with running(reader):
        await asyncio.sleep(0.1)
        assert reader.health().state is LinkState.CONNECTING
        beacons.append(FakeBeacon(tmp_path / "usb-Marvelmind_Hedgehog-if00"))
        await stream_until(beacons[0], received, 1, 1.0, timeout=2.0)


async def test_a_failing_consumer_stops_the_reader(link: Path, beacons: list[FakeBeacon]) -> None:
    beacons.append(FakeBeacon(link))

    def broken(event: Event) -> None:
        raise RuntimeError("consumer bug")

    reader = MarvelmindReader(MarvelmindConfig(device=str(link)), broken)
    task = asyncio.create_task(reader.run())
    deadline = time.monotonic() + 3.0
    while not task.done():
        assert time.monotonic() < deadline
        beacons[0].send_fix()
        await asyncio.sleep(0.01)
    with pytest.raises(RuntimeError, match="consumer bug"):
        task.result()


def test_backoff_doubles_up_to_its_cap_and_resets() -> None:
    backoff = Backoff(0.05, 0.3)
    assert [backoff.next_delay() for _ in range(5)] == [0.05, 0.1, 0.2, 0.3, 0.3]
    backoff.reset()
    assert backoff.next_delay() == 0.05


def test_resolve_device(tmp_path: Path) -> None:
    assert resolve_device("/dev/ttyACM0") == "/dev/ttyACM0"
    assert resolve_device(str(tmp_path / "x*")) is None
    for name in ("x2", "x1"):
        (tmp_path / name).touch()
    assert resolve_device(str(tmp_path / "x*")) == str(tmp_path / "x1")
