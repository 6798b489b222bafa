"""L298 motor outputs through gpiozero on the virtual pigpiod; zeroed on raise, SIGTERM and by stop-motors."""

from __future__ import annotations

import signal
import socket
import subprocess
import time
from dataclasses import replace
from pathlib import Path

import pytest
from process_support import python_child
from wheels_support import wait_until

from drivers.pigpiod.client import PigpiodUnavailableError
from drivers.pigpiod.protocol import Mode
from drivers.virtual.pigpiod import VirtualPigpiod
from drivers.wheels.motors import GpiozeroMotors, command_duty, stop_all_motors, wheel_pins
from robotd.cli import main
from robotd.config.model import MotorsConfig, PigpiodConfig

SPIN_ARGS = ["--duty", "0.5", "-0.3", "0.2", "0.9", "--seconds", "60"]


def outputs(server: VirtualPigpiod, motors: MotorsConfig) -> list[tuple[float, int, int]]:
    """(enable duty, IN1, IN2) per wheel as the virtual pigpiod holds them."""
    return [(server.pwm_duty(p.enable), server.level(p.in1), server.level(p.in2)) for p in wheel_pins(motors)]


def test_duties_set_direction_pins_and_enable_pwm(server: VirtualPigpiod) -> None:
    motors = MotorsConfig()
    with GpiozeroMotors(motors, PigpiodConfig(port=server.port)) as outputs_:
        assert outputs(server, motors) == [(0.0, 0, 0)] * 4  # zero from the start
        outputs_.set_duties((0.5, -0.25, 0.0, 1.0))  # sent without waiting: pigpiod carries it out a moment later
        wait_until(lambda: outputs(server, motors) == [(0.5, 1, 0), (0.25, 0, 1), (0.0, 0, 0), (1.0, 1, 0)])
        outputs_.set_duties((-0.5, -0.25, 0.1, 0.0))  # a reversal, an unchanged wheel, a start, a stop
        wait_until(lambda: outputs(server, motors) == [(0.5, 0, 1), (0.25, 0, 1), (0.1, 1, 0), (0.0, 0, 0)])
        assert server.pwm_frequency(motors.wheels.front_left.enable) == motors.pwm_frequency_hz


def test_limit_and_wheel_sign_are_applied(server: VirtualPigpiod) -> None:
    motors = replace(MotorsConfig(), duty_limit=0.6)
    wheels = replace(motors.wheels, front_right=replace(motors.wheels.front_right, sign=-1))
    motors = replace(motors, wheels=wheels)
    with GpiozeroMotors(motors, PigpiodConfig(port=server.port)) as outputs_:
        outputs_.set_duties((0.9, 0.3, -2.0, float("nan")))
        wait_until(lambda: outputs(server, motors) == [(0.6, 1, 0), (0.3, 0, 1), (0.6, 0, 1), (0.0, 0, 0)])
    assert command_duty(0.3, -1, 1.0) == -0.3


def test_motors_are_zeroed_when_the_program_raises(server: VirtualPigpiod) -> None:
    motors = MotorsConfig()

    def control_loop_that_fails() -> None:
        with GpiozeroMotors(motors, PigpiodConfig(port=server.port)) as running:
            running.set_duties((0.7, 0.7, -0.7, -0.7))
            wait_until(lambda: server.pwm_duty(motors.wheels.front_left.enable) == pytest.approx(0.7))
            raise RuntimeError("control loop failed")

    with pytest.raises(RuntimeError, match="control loop failed"):
        control_loop_that_fails()
    assert [duty for duty, _, _ in outputs(server, motors)] == [0.0] * 4


def test_close_ends_the_pigpio_client_thread(server: VirtualPigpiod) -> None:
    motors = GpiozeroMotors(MotorsConfig(), PigpiodConfig(port=server.port))
    thread = motors._pi._notify  # pigpio's notification thread for this client
    motors.set_duties((0.4, -0.4, 0.4, 0.4))
    motors.close()
    # Left running, it would read its socket after pigpiod closed it (a reset raised in the thread, at random)
    assert not thread.is_alive()
    wait_until(lambda: server.notify_handles() == {})  # pigpiod freed the handle with the socket


def test_close_after_pigpiod_went_away_ends_the_client_thread() -> None:
    with VirtualPigpiod() as gone:
        motors = GpiozeroMotors(MotorsConfig(), PigpiodConfig(port=gone.port, connect_timeout_s=0.5))
        thread = motors._pi._notify
    time.sleep(0.05)  # pigpio's thread now loops on the closed socket's end-of-file
    assert thread.is_alive()
    motors.close()
    assert not thread.is_alive()


def test_stop_all_motors_leaves_every_motor_pin_an_output_driven_low(server: VirtualPigpiod) -> None:
    motors = MotorsConfig()
    pigpiod = PigpiodConfig(port=server.port)
    outputs_ = GpiozeroMotors(motors, pigpiod)
    outputs_.set_duties((0.4, 0.4, 0.4, 0.4))
    stop_all_motors(motors, pigpiod)  # as ExecStopPost would, while the crashed owner still holds the pins
    assert outputs(server, motors) == [(0.0, 0, 0)] * 4
    assert {server.mode(p.enable) for p in wheel_pins(motors)} == {Mode.OUTPUT}
    outputs_.close()


def test_unreachable_pigpiod_is_a_clear_error_and_exit_69(tmp_path: Path) -> None:
    with socket.socket() as placeholder:
        placeholder.bind(("127.0.0.1", 0))
        port = placeholder.getsockname()[1]
        with pytest.raises(PigpiodUnavailableError, match="not reachable"):
            stop_all_motors(MotorsConfig(), PigpiodConfig(port=port, connect_timeout_s=0.5))
        config = tmp_path / "robot.yaml"
        config.write_text(f"pigpiod:\n  port: {port}\n")
        assert main(["stop-motors", "--config", str(config)]) == 69


def _spin_wheels(config: Path) -> subprocess.Popen[str]:
    return python_child(["-m", "robotd", "spin-wheels", "--config", str(config), *SPIN_ARGS], stderr=subprocess.PIPE)


def test_sigterm_to_a_process_driving_the_motors_leaves_them_at_zero(server: VirtualPigpiod, tmp_path: Path) -> None:
    motors = MotorsConfig()
    config = tmp_path / "robot.yaml"
    config.write_text(f"pigpiod:\n  port: {server.port}\n")
    process = _spin_wheels(config)
    try:
        wait_until(lambda: server.pwm_duty(motors.wheels.rear_right.enable) > 0.8 or process.poll() is not None, 20)
        assert outputs(server, motors) == [(0.5, 1, 0), (0.3, 0, 1), (0.2, 1, 0), (0.9, 1, 0)]
        process.send_signal(signal.SIGTERM)
        _, stderr = process.communicate(timeout=20)
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
    assert process.returncode == 128 + signal.SIGTERM, stderr
    assert [duty for duty, _, _ in outputs(server, motors)] == [0.0] * 4


def test_after_a_kill_stop_motors_zeroes_what_the_dead_process_left(server: VirtualPigpiod, tmp_path: Path) -> None:
    motors = MotorsConfig()
    config = tmp_path / "robot.yaml"
    config.write_text(f"pigpiod:\n  port: {server.port}\n")
    process = _spin_wheels(config)
    try:
        wait_until(lambda: server.pwm_duty(motors.wheels.rear_right.enable) > 0.8 or process.poll() is not None, 20)
        process.kill()  # SIGKILL: no handler runs, the outputs stay as they were
        process.communicate(timeout=20)
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
    assert server.pwm_duty(motors.wheels.front_left.enable) == pytest.approx(0.5)
    assert main(["stop-motors", "--config", str(config)]) == 0
    assert outputs(server, motors) == [(0.0, 0, 0)] * 4
