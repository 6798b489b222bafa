"""Shared fixtures of the tools' tests."""

from __future__ import annotations

import os
import pty
import tty
from collections.abc import Iterator

import pytest


@pytest.fixture
def beacon_pty() -> Iterator[tuple[int, str]]:
    """A pseudo-terminal: (master to write frames into, path of the device to read)."""
    master, slave = pty.openpty()
    tty.setraw(slave)
    try:
        yield master, os.ttyname(slave)
    finally:
        os.close(master)
        os.close(slave)
