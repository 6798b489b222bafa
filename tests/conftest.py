"""Fixtures shared across the suite: a virtual pigpiod, the real pigpio client connected to it, a beacon pty.

Helpers that tests import by name (`daemon_support`, `paths`, ...) live in tests/support, which pytest puts on the
import path (pyproject's `pythonpath`); tests import in importlib mode, so no test folder shadows the packages.
"""

from __future__ import annotations

import os
import pty
import tty
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pigpio
import pytest
from mosquitto import mosquitto, write_key

from drivers.pigpiod.client import stop_pigpio_client
from drivers.virtual.pigpiod import VirtualPigpiod
from robotd.fleet.broker import Broker


@pytest.fixture
def server() -> Iterator[VirtualPigpiod]:
    """A virtual pigpiod on a free loopback port, stopped after the test."""
    with VirtualPigpiod() as running:
        yield running


@pytest.fixture
def pi(server: VirtualPigpiod) -> Iterator[Any]:
    """The real `pigpio` client connected to `server`."""
    client = pigpio.pi("127.0.0.1", server.port, show_errors=False)
    assert client.connected
    yield client
    stop_pigpio_client(client)


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


@pytest.fixture
def broker(tmp_path: Path) -> Iterator[Broker]:
    """A real mosquitto with users robot-r1, robot-r2 and operator, each with its ACL (skips without mosquitto)."""
    with mosquitto(tmp_path / "broker", ("r1", "r2")) as running:
        yield running


@pytest.fixture
def fleet_key(tmp_path: Path) -> tuple[Path, bytes]:
    """A private fleet key file and its key."""
    path = tmp_path / "fleet.key"
    return path, write_key(path)
