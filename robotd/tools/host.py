"""What the robot's computer is: its board (from the device tree) and its serial devices by id.

A Raspberry Pi 5 (and the 500 and Compute Module 5, on the same RP1 I/O chip) cannot run pigpio; every earlier Pi
can. udev names each USB serial device `/dev/serial/by-id/usb-<vendor>_<model>_<serial>-if<NN>`: the serial number is
what tells two beacons with the same generic STM32 USB id (0483:5740) apart.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from drivers.board import MODEL_FILE, RP1_BOARDS, Board, board_of, read_model

BY_ID_DIR = "dev/serial/by-id"
SERIAL_PATTERN = re.compile(r"[A-Za-z0-9._-]{1,64}")
"""A serial number robotd writes into a udev rule: no quotes, spaces or glob characters."""

__all__ = ["MODEL_FILE", "RP1_BOARDS", "Board", "SerialDevice", "board_of", "read_model", "serial_devices", "serial_of"]


@dataclass(frozen=True, slots=True)
class SerialDevice:
    """A USB serial device as udev lists it under /dev/serial/by-id."""

    name: str  # the by-id link's name
    serial: str  # the USB serial number (udev's ID_SERIAL_SHORT)
    target: str  # what the link points to, e.g. ../../ttyACM0


def serial_of(by_id_name: str) -> str | None:
    """The USB serial number in a by-id name (`usb-Vendor_Model_SERIAL-if00`), or None when it has none."""
    match = re.fullmatch(r"usb-.+_([^_]+)-if\d+(?:-port\d+)?", by_id_name)
    return match.group(1) if match else None


def serial_devices(root: Path) -> list[SerialDevice]:
    """The USB serial devices under `root`'s /dev/serial/by-id, sorted by name."""
    directory = root / BY_ID_DIR
    if not directory.is_dir():
        return []
    found = []
    for link in sorted(directory.iterdir()):
        serial = serial_of(link.name)
        if serial is not None:
            target = str(link.readlink()) if link.is_symlink() else link.name
            found.append(SerialDevice(link.name, serial, target))
    return found


def serial_problem(serial: str) -> str | None:
    """Why `serial` cannot go into a udev rule, or None when it can."""
    if SERIAL_PATTERN.fullmatch(serial):
        return None
    return f"{serial!r} is not a USB serial number (letters, digits, '.', '_', '-'; at most 64)"
