"""`robotd stop-motors` (the unit's ExecStopPost) stops the motors whatever is wrong with the configuration file.

Each test drives motor pins through the real pigpio client on the virtual pigpiod, as a crashed daemon leaves them,
runs the real command line on a broken file, and checks the pins are outputs driven low afterwards.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pigpio
import pytest
from paths import REPO

from drivers.pigpiod.client import stop_pigpio_client
from drivers.pigpiod.protocol import Mode
from drivers.virtual.pigpiod import VirtualPigpiod
from robotd.cli import main
from robotd.config.model import WHEELS, MotorsConfig, PigpiodConfig
from robotd.config.motorpins import read_stop_targets

DEFAULT_PINS = [getattr(MotorsConfig().wheels, wheel) for wheel in WHEELS]
# front_left moved to pins 7, 8, 9: a file read correctly stops these, not the built-in 12, 16, 20
CUSTOM_MOTORS = "motors:\n  wheels:\n    front_left: {enable: 7, in1: 8, in2: 9}\n"
CUSTOM_PINS = [(7, 8, 9)] + [(p.enable, p.in1, p.in2) for p in DEFAULT_PINS[1:]]
BUILT_IN_PINS = [(p.enable, p.in1, p.in2) for p in DEFAULT_PINS]

pytestmark = pytest.mark.timeout(30)


@pytest.fixture
def default_server() -> Iterator[VirtualPigpiod]:
    """A virtual pigpiod at the built-in address (127.0.0.1:8888), where a file that cannot be read sends the stop."""
    default = PigpiodConfig()
    try:
        running = VirtualPigpiod(default.host, default.port).start()
    except OSError as error:
        pytest.skip(f"{default.host}:{default.port} is taken on this machine: {error}")
    try:
        yield running
    finally:
        running.stop()


def drive(server: VirtualPigpiod, pins: list[tuple[int, int, int]]) -> None:
    """Leave every wheel running forward at 95 % duty, as a daemon killed mid-drive does."""
    pi: Any = pigpio.pi("127.0.0.1", server.port, show_errors=False)
    assert pi.connected
    try:
        for enable, in1, in2 in pins:
            pi.write(in1, 1)
            pi.write(in2, 0)
            pi.set_PWM_dutycycle(enable, 242)
    finally:
        stop_pigpio_client(pi)
    assert all(server.pwm_duty(enable) > 0.9 for enable, _, _ in pins)


def assert_stopped(server: VirtualPigpiod, pins: list[tuple[int, int, int]]) -> None:
    """Every pin an output, driven low."""
    for wheel in pins:
        assert [(server.mode(gpio), server.level(gpio)) for gpio in wheel] == [(Mode.OUTPUT, 0)] * 3, wheel


def stop_motors(path: Path, capsys: pytest.CaptureFixture[str]) -> tuple[int, list[str]]:
    """Run `robotd stop-motors --config path` in-process: exit status and stderr lines."""
    status = main(["stop-motors", "--config", str(path)])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return status, err.splitlines()


def test_an_invalid_unrelated_field_does_not_stop_the_stop(
    server: VirtualPigpiod, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = tmp_path / "robot.yaml"
    config.write_text(f"ekf:\n  ips_sigma_m: -0.03\n{CUSTOM_MOTORS}pigpiod: {{port: {server.port}}}\n")
    drive(server, CUSTOM_PINS)
    status, err = stop_motors(config, capsys)
    assert status == 0
    assert err == []  # it read all it needed: nothing to say
    assert_stopped(server, CUSTOM_PINS)


def test_a_non_number_in_a_list_does_not_crash_it(
    server: VirtualPigpiod, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = tmp_path / "robot.yaml"
    config.write_text(f"ekf:\n  initial_sigma: [1.0, oops, 3.14]\n{CUSTOM_MOTORS}pigpiod: {{port: {server.port}}}\n")
    drive(server, CUSTOM_PINS)
    assert stop_motors(config, capsys) == (0, [])
    assert_stopped(server, CUSTOM_PINS)


def test_a_bad_pin_falls_back_to_that_pins_default_and_says_so(
    server: VirtualPigpiod, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = tmp_path / "robot.yaml"
    config.write_text(
        "motors:\n  wheels:\n    front_left: {enable: 7, in1: [8], in2: 40}\n    rear_left: 5\n"
        f"pigpiod: {{port: {server.port}, connect_timeout_s: 1.0e+9}}\n"
    )
    pins = [(7, 16, 20), *BUILT_IN_PINS[1:]]
    drive(server, pins)
    status, err = stop_motors(config, capsys)
    assert status == 0
    assert any(line.startswith("robotd stop-motors: motors.wheels.front_left.in1: ") for line in err), err
    assert any("motors.wheels.front_left.in2: " in line and line.endswith("using GPIO 20") for line in err), err
    assert any("motors.wheels.rear_left: expected a mapping" in line for line in err), err
    assert any("pigpiod.connect_timeout_s: " in line and line.endswith("using 2.0") for line in err), err
    assert_stopped(server, pins)


@pytest.mark.parametrize(
    "broken",
    [
        pytest.param(None, id="missing file"),
        pytest.param(b"motors: [unclosed\n  wheels: {", id="garbage YAML"),
        pytest.param(b"\xff\xfe not text", id="not UTF-8"),
        pytest.param("directory", id="a directory"),
        pytest.param(b"a: &x [1]\nb: *x\n", id="an alias"),
    ],
)
def test_a_file_it_cannot_read_stops_the_built_in_pins_on_the_built_in_pigpiod(
    default_server: VirtualPigpiod, tmp_path: Path, capsys: pytest.CaptureFixture[str], broken: bytes | str | None
) -> None:
    config = tmp_path / "robot.yaml"
    if broken == "directory":
        config.mkdir()
    elif isinstance(broken, bytes):
        config.write_bytes(broken)
    drive(default_server, BUILT_IN_PINS)
    status, err = stop_motors(config, capsys)
    assert status == 0
    assert len(err) == 1, err
    assert err[0].startswith(f"robotd stop-motors: {config}: ")
    assert "using the built-in motor pins" in err[0]
    assert err[0].endswith("and pigpiod 127.0.0.1:8888")
    assert_stopped(default_server, BUILT_IN_PINS)


def test_unreachable_pigpiod_is_exit_69_even_with_a_broken_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with VirtualPigpiod() as gone:
        port = gone.port  # a port nothing listens on once the server is stopped
    config = tmp_path / "robot.yaml"
    config.write_text(f"ekf: {{ips_sigma_m: -1}}\npigpiod: {{port: {port}, connect_timeout_s: 0.5}}\n")
    status, err = stop_motors(config, capsys)
    assert status == 69
    assert any("not reachable" in line for line in err), err


def test_the_unit_command_line_in_a_process(server: VirtualPigpiod, tmp_path: Path) -> None:
    """As systemd runs it after a crash: a separate process, a file broken elsewhere, exit 0 and the pins low."""
    config = tmp_path / "robot.yaml"
    config.write_text(f"teleop: {{deadman_timeout_s: -1}}\n{CUSTOM_MOTORS}pigpiod: {{port: {server.port}}}\n")
    drive(server, CUSTOM_PINS)
    result = subprocess.run(
        [sys.executable, "-m", "robotd", "stop-motors", "--config", str(config)],
        cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        capture_output=True,
        text=True,
        timeout=20,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    assert "Traceback" not in result.stderr
    assert_stopped(server, CUSTOM_PINS)


def test_the_reader_reads_nothing_but_the_pins_and_the_address(tmp_path: Path) -> None:
    config = tmp_path / "robot.yaml"
    config.write_text(
        "robot: 5\nencoders: {wheels: {front_left: {a: 99}}}\n"
        "motors: {duty_limit: 7, wheels: {rear_right: {enable: 10, sign: 3, colour: red}}}\n"
        "pigpiod: {host: pi.local, port: 9999, reconnect_max_s: -1}\n"
    )
    targets = read_stop_targets(str(config))
    assert targets.fallbacks == ()
    assert (targets.motors.wheels.rear_right.enable, targets.motors.wheels.rear_right.in1) == (10, 25)
    assert (targets.pigpiod.host, targets.pigpiod.port) == ("pi.local", 9999)
    assert read_stop_targets(None).motors == MotorsConfig()
