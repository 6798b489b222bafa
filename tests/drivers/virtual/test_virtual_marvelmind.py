"""The virtual Marvelmind: frames on a real pseudo-terminal, dropped while nobody listens, parsed by the real parser."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from drivers.marvelmind.events import FixUnavailable, Position, StationaryBeacons
from drivers.marvelmind.protocol import MarvelmindParser
from drivers.virtual.marvelmind import (
    POSITION_CM,
    POSITION_MM,
    HedgehogPacket,
    VirtualMarvelmind,
    beacons_frame,
    position_frame,
)


def _packet(code: int, available: bool = True) -> HedgehogPacket:
    return HedgehogPacket(
        arrival_s=10.0, measured_s=9.9, timestamp_ms=4_294_967_000 + (0 if available else 80),
        x_mm=1230, y_mm=-4560, z_mm=300, available=available, time_shift_ms=100, address=7, frame_code=code,
    )  # fmt: skip


@pytest.mark.parametrize("code", [POSITION_MM, POSITION_CM])
def test_packets_become_frames_the_parser_reads_back(code: int) -> None:
    parser = MarvelmindParser()
    (fix,) = parser.feed(position_frame(_packet(code)), arrival=10.0)
    assert isinstance(fix, Position)
    assert fix.code == code
    assert (fix.x, fix.y, fix.z) == (1.23, -4.56, 0.3)
    assert fix.t_meas == pytest.approx(9.9)
    assert fix.heading_rad is None
    (lost,) = parser.feed(position_frame(_packet(code, available=False)), arrival=10.1)
    assert isinstance(lost, FixUnavailable)
    (beacons,) = parser.feed(beacons_frame([(-1.0, 1.0, 2.0), (4.0, 1.0, 2.0)], code), arrival=10.2)
    assert isinstance(beacons, StationaryBeacons)
    assert [(b.address, b.x, b.y, b.z) for b in beacons.beacons] == [(1, -1.0, 1.0, 2.0), (2, 4.0, 1.0, 2.0)]


def test_frames_reach_whoever_opens_the_link_and_nobody_else(tmp_path: Path) -> None:
    link = tmp_path / "dev" / "marvelmind"
    device = VirtualMarvelmind(str(link))
    try:
        assert os.path.realpath(link) == device.slave_path
        frame = position_frame(_packet(POSITION_MM))
        assert not device.write(frame)  # nobody listens: dropped, not queued for a later reader
        reader = os.open(link, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        try:
            with pytest.raises(BlockingIOError):
                os.read(reader, 1024)
            assert device.write(frame)
            assert os.read(reader, 1024) == frame  # raw mode: every byte as written
        finally:
            os.close(reader)
        assert (device.frames_written, device.frames_unheard) == (1, 1)
    finally:
        device.close()
    assert not os.path.lexists(link)  # unplugged: the link goes with the device
