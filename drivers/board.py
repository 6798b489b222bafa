"""Which board this is, from the device tree's model string: an RP1 board (Raspberry Pi 5 family) or an earlier Pi.

A Raspberry Pi 5 (and the 500 and Compute Module 5, on the same RP1 I/O chip) cannot run pigpio; every earlier Pi
can. The device tree names the board in /proc/device-tree/model (NUL-terminated); a machine without one is not a Pi.
"""

from __future__ import annotations

import enum
from pathlib import Path

MODEL_FILE = "proc/device-tree/model"
RP1_BOARDS = ("Raspberry Pi 5", "Raspberry Pi 500", "Raspberry Pi Compute Module 5")


class Board(enum.Enum):
    """The board families robotd runs and installs differently on."""

    PI4 = "pi4"  # a Raspberry Pi 4 or earlier: pigpio runs, pigpiod's drop-in is installed
    PI5 = "pi5"  # an RP1 board: no pigpio (the gpiod back-end)

    @property
    def uses_pigpio(self) -> bool:
        """True when robotd drives the GPIO through pigpiod on this board."""
        return self is Board.PI4


def read_model(root: Path) -> str | None:
    """The board's model string from the device tree under `root`, or None when there is none (not a Pi)."""
    try:
        return (root / MODEL_FILE).read_bytes().rstrip(b"\0\n").decode("utf-8", "replace")
    except OSError:
        return None


def board_of(model: str) -> Board | None:
    """The board family of a device-tree model string, or None when it is not a Raspberry Pi."""
    if model.startswith(RP1_BOARDS):
        return Board.PI5
    if model.startswith("Raspberry Pi"):
        return Board.PI4
    return None


def this_board(root: Path = Path("/")) -> Board | None:
    """The board family of the machine whose root directory is `root`, or None when it is not a Raspberry Pi."""
    model = read_model(root)
    return board_of(model) if model is not None else None
