"""How the daemon says why it stopped: a bug at ERROR with its traceback, an operational failure in one line."""

from __future__ import annotations

import logging
from pathlib import Path

import pigpio
import pytest
from inprocess_daemon import FakeEncoders, FakeMotors, daemon_config, running

from drivers.pigpiod.client import PigpioCommandError
from robotd.daemon.service import Daemon


async def stopped_by(tmp_path: Path, failure: BaseException, caplog: pytest.LogCaptureFixture) -> logging.LogRecord:
    """Run a daemon whose encoder source raises `failure`; its exit status must be 1 and its ERROR line is returned."""
    encoders = FakeEncoders(lambda: 0.0)
    encoders.fail_with = failure
    motors = FakeMotors()
    daemon = Daemon(daemon_config(tmp_path), encoders=encoders, motors_factory=lambda: motors)
    async with running(daemon) as task:
        status = await task
    assert status == 1
    assert motors.closed, "the motors are zeroed and released on the way out"
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR and r.name == "robotd"]
    assert len(errors) == 1, [r.getMessage() for r in errors]
    return errors[0]


def raise_a_bug() -> None:
    wheels: dict[str, int] = {}
    wheels["front_left"] += 1  # the bug: a KeyError deep in a producer


async def test_an_unexpected_exception_is_logged_at_error_with_its_traceback(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    try:
        raise_a_bug()
    except KeyError as bug:
        failure = bug
    record = await stopped_by(tmp_path, failure, caplog)
    assert record.getMessage() == "robotd stopping after an unexpected error: KeyError: 'front_left'"
    assert record.exc_info is not None
    assert "in raise_a_bug" in caplog.text, "the traceback reaches the log, down to the function that failed"


@pytest.mark.parametrize(
    "failure",
    [
        ConnectionResetError("pigpiod closed the connection"),
        OSError(5, "Input/output error"),
        PigpioCommandError(4, 12, 1, -41),  # WRITE refused
        pigpio.error("pigpio socket closed"),
    ],
    ids=["connection", "eio", "pigpio-command", "pigpio-library"],
)
async def test_an_operational_failure_is_one_line_without_a_traceback(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, failure: Exception
) -> None:
    record = await stopped_by(tmp_path, failure, caplog)
    assert record.getMessage().startswith(f"robotd stopping after a failure: {type(failure).__name__}: ")
    assert record.exc_info is None
    assert "Traceback" not in caplog.text
