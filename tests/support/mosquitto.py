"""A real `mosquitto` for the fleet tests: generated users and ACLs (robotd.fleet.broker), on a free loopback port.

Without mosquitto (`make test` installs it as root: `apt-get install -y mosquitto`) the tests that need it skip,
saying why; with CI=true that skip is a failure, so CI never passes without the broker.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from robotd.fleet.broker import Broker, BrokerSetup, find_program

MISSING = "mosquitto is not installed (`make test` installs it when run as root: apt-get install -y mosquitto)"


def require_mosquitto() -> None:
    """Skip the test without mosquitto and mosquitto_passwd; fail it instead under CI=true."""
    if find_program("mosquitto") and find_program("mosquitto_passwd"):
        return
    if os.environ.get("CI", "").lower() == "true":
        pytest.fail(f"{MISSING}; CI must run the fleet tests")
    pytest.skip(MISSING)


@contextlib.contextmanager
def mosquitto(folder: Path, robot_ids: tuple[str, ...]) -> Iterator[Broker]:
    """A broker for `robot_ids` (and the operator) running in `folder`; stopped on the way out."""
    require_mosquitto()
    with Broker(BrokerSetup(folder, robot_ids)) as broker:
        yield broker


def fleet_section(broker: Broker, robot_id: str, key_file: Path, **extra: object) -> dict[str, object]:
    """The `fleet` configuration section of a robot on `broker`."""
    setup = broker.setup
    from robotd.fleet.broker import robot_user  # noqa: PLC0415 - beside its only use

    return {
        "enabled": True,
        "robot_id": robot_id,
        "host": "127.0.0.1",
        "port": setup.port,
        "credentials_file": str(setup.credentials_file(robot_user(robot_id))),
        "key_file": str(key_file),
        **extra,
    }


def write_key(path: Path, key: bytes = b"fleet-key-for-the-tests-0123456789") -> bytes:
    """A private fleet key file; returns the key."""
    path.write_bytes(key)
    path.chmod(0o600)
    return key
