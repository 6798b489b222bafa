"""Fixtures shared across the suite: a virtual pigpiod and the real pigpio client connected to it.

Helpers that tests import by name (`daemon_support`, `paths`, ...) live in tests/support, which pytest puts on the
import path (pyproject's `pythonpath`); tests import in importlib mode, so no test folder shadows the packages.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pigpio
import pytest

from drivers.virtual.pigpiod import VirtualPigpiod


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
    client.stop()
