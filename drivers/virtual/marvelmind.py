"""The virtual Marvelmind: real streaming frames written to a pseudo-terminal that the daemon opens as its serial port.

Theory of operation: `pty.openpty()` gives a master and a slave; the slave is put in raw mode (no line discipline may
touch a 0x0A or 0x0D inside a frame) and closed again, so that only the daemon holds it. Each hedgehog packet is
encoded by the Marvelmind driver's own frame encoders (code 0x0011 or 0x0001, flags bit 1 for millisecond timestamps,
bit 0 for "coordinates unavailable", heading marked not applicable, the time-shift field filled), and so are the
stationary beacons' frames. A USB serial device drops what nobody reads: while no process holds the slave open (the
master polls POLLHUP) frames are counted and dropped, never queued for a reader that comes later. A path in the
configuration may be linked to the slave, as udev links the real device. `close()` ends the master: to the daemon,
an unplugged device.

Not modelled: the IMU, telemetry and quality frames, the 64-bit-timestamp codes, UART baud rates, writes from the
host (a real hedgehog pauses streaming for 5 s; here they are read and ignored).
"""

from __future__ import annotations

import contextlib
import os
import pty
import select
import tty
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from drivers.marvelmind.events import ANGLE_HEADING_NOT_APPLICABLE, StationaryBeacon
from drivers.marvelmind.frames import encode_beacons_cm, encode_beacons_mm, encode_position_cm, encode_position_mm

POSITION_CM = 0x0001
POSITION_MM = 0x0011
FLAG_UNAVAILABLE = 0x01


@dataclass(frozen=True, slots=True)
class HedgehogPacket:
    """One position packet as the hedgehog sends it, with when it reaches the host."""

    arrival_s: float  # when its last byte reaches the host (simulated time)
    measured_s: float  # when the ultrasound was emitted (true)
    timestamp_ms: int  # the beacon's own u32 millisecond clock
    x_mm: int
    y_mm: int
    z_mm: int
    available: bool  # False: "coordinates unavailable" (flags bit 0)
    time_shift_ms: int  # measurement to sending, as the frame's time-shift field says
    address: int
    frame_code: int

    @property
    def measured_by_host_s(self) -> float:
        """The measurement time a host computes from the arrival and the time-shift field."""
        return self.arrival_s - self.time_shift_ms / 1000.0


FLAG_MILLISECONDS = 0x02


def position_frame(packet: HedgehogPacket) -> bytes:
    """The streaming frame that carries a hedgehog packet."""
    encode = encode_position_cm if packet.frame_code == POSITION_CM else encode_position_mm
    flags = FLAG_MILLISECONDS | (0 if packet.available else FLAG_UNAVAILABLE)
    return encode(
        packet.timestamp_ms,
        packet.x_mm / 1000.0,
        packet.y_mm / 1000.0,
        packet.z_mm / 1000.0,
        packet.address,
        flags=flags,
        time_shift_ms=packet.time_shift_ms,
        angle_word=ANGLE_HEADING_NOT_APPLICABLE,
    )


def beacons_frame(positions: Sequence[tuple[float, float, float]], frame_code: int) -> bytes:
    """The stationary beacons' frame (addresses 1, 2, ...), in the unit of the position frames."""
    beacons = [StationaryBeacon(i + 1, x, y, z) for i, (x, y, z) in enumerate(positions)]
    return encode_beacons_cm(beacons) if frame_code == POSITION_CM else encode_beacons_mm(beacons)


class VirtualMarvelmind:
    """A pseudo-terminal streaming frames; `slave_path` is the device, `link` its configured alias."""

    def __init__(self, link: str | None = None) -> None:
        self._master, slave = pty.openpty()
        try:
            tty.setraw(slave)
            self.slave_path = os.ttyname(slave)
        finally:
            os.close(slave)
        os.set_blocking(self._master, False)
        self._poll = select.poll()
        self._poll.register(self._master, select.POLLOUT)
        self.link = Path(link) if link else None
        if self.link is not None:
            self.link.parent.mkdir(parents=True, exist_ok=True)
            with contextlib.suppress(FileNotFoundError):
                if self.link.is_symlink() or self.link.exists():
                    self.link.unlink()  # a stale link from an earlier run (or a file we were told to replace)
            self.link.symlink_to(self.slave_path)
        self.frames_written = 0
        self.frames_unheard = 0
        self.bytes_dropped = 0

    @property
    def is_open(self) -> bool:
        """Whether the master is still open."""
        return self._master >= 0

    def listening(self) -> bool:
        """Whether some process holds the device open."""
        return self.is_open and not any(events & select.POLLHUP for _, events in self._poll.poll(0))

    def write(self, frame: bytes) -> bool:
        """Send one frame if somebody listens; True if it was sent whole."""
        if not self.listening():
            self.frames_unheard += 1
            return False
        with contextlib.suppress(OSError):
            while os.read(self._master, 4096):  # the daemon must not write; if it does, the bytes are ignored
                pass
        try:
            written = os.write(self._master, frame)
        except (BlockingIOError, OSError):
            written = 0
        if written < len(frame):  # a reader too slow for the line: the rest is lost, as on a full USB buffer
            self.bytes_dropped += len(frame) - written
            return False
        self.frames_written += 1
        return True

    def close(self) -> None:
        """Unplug: close the master and remove the link."""
        if self._master >= 0:
            os.close(self._master)
            self._master = -1
        if self.link is not None and self.link.is_symlink() and os.readlink(self.link) == self.slave_path:
            self.link.unlink()
