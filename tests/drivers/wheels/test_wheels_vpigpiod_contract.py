"""The real pigpio client and gpiozero's PiGPIOFactory against the virtual pigpiod."""

from __future__ import annotations

import asyncio
import signal
import socket
import struct
import threading
from collections.abc import Iterator
from typing import Any

import numpy as np
import pigpio
import pytest
from gpiozero import DigitalInputDevice, DigitalOutputDevice, PWMOutputDevice
from gpiozero.pins.pigpio import PiGPIOFactory
from process_support import python_child
from wheels_support import wait_until

from drivers.pigpiod.client import end_pigpio_notifications, stop_pigpio_client
from drivers.pigpiod.protocol import COMMAND, REPORT_SIZE, Cmd, decode_reports, decode_result, encode_command
from drivers.virtual.pigpiod import PI4B_4GB, VirtualPigpiod

NEAR_WRAP = (1 << 32) - 50_000  # a tick 50 ms before pigpio's 32-bit tick wraps


@pytest.fixture
def server() -> Iterator[VirtualPigpiod]:
    """The shared `server` fixture's pigpiod, started near the tick wrap (the shared `pi` connects to this one)."""
    with VirtualPigpiod(start_tick=NEAR_WRAP) as running:
        yield running


@pytest.fixture
def factory(server: VirtualPigpiod) -> Iterator[Any]:
    pin_factory = PiGPIOFactory(host="127.0.0.1", port=server.port)
    yield pin_factory
    end_pigpio_notifications(pin_factory.connection)  # gpiozero's close releases its pins, then stops the client
    pin_factory.close()


def test_pigpio_sees_a_pi_4b_whose_tick_follows_the_clock(server: VirtualPigpiod, pi: Any) -> None:
    assert pi.get_hardware_revision() == PI4B_4GB
    first = pi.get_current_tick()
    second = pi.get_current_tick()
    assert 0 <= pigpio.tickDiff(first, second) < 100_000
    assert pigpio.tickDiff(NEAR_WRAP, first) < 2_000_000


def test_pigpio_modes_pulls_reads_and_writes(server: VirtualPigpiod, pi: Any) -> None:
    pi.set_mode(23, pigpio.INPUT)
    pi.set_pull_up_down(23, pigpio.PUD_UP)
    assert pi.read(23) == 1
    pi.set_pull_up_down(23, pigpio.PUD_DOWN)
    assert pi.read(23) == 0
    assert (server.mode(23), server.pull(23)) == (pigpio.INPUT, pigpio.PUD_DOWN)
    pi.write(24, 1)
    assert pi.get_mode(24) == pigpio.OUTPUT
    assert server.level(24) == 1
    assert pi.read_bank_1() & (1 << 24)
    pi.set_mode(5, pigpio.ALT0)
    assert pi.get_mode(5) == pigpio.ALT0


def test_pigpio_pwm_settings_and_their_errors(server: VirtualPigpiod, pi: Any) -> None:
    assert pi.set_PWM_frequency(18, 1100) == 1000  # snapped to the nearest frequency pigpio offers
    assert pi.get_PWM_frequency(18) == 1000
    assert pi.set_PWM_range(18, 1000) == 200  # the real range at 1 kHz
    pi.set_PWM_dutycycle(18, 250)
    assert pi.get_PWM_dutycycle(18) == 250
    assert server.pwm_duty(18) == pytest.approx(0.25)
    pi.set_PWM_range(18, 2000)  # an active duty is rescaled to the new range
    assert pi.get_PWM_dutycycle(18) == 500
    with pytest.raises(pigpio.error, match="dutycycle"):
        pi.set_PWM_dutycycle(18, 2001)
    pi.write(18, 0)  # a write stops PWM
    with pytest.raises(pigpio.error, match="not in use for PWM"):
        pi.get_PWM_dutycycle(18)
    with pytest.raises(pigpio.error, match="GPIO not 0-31"):
        pi.set_PWM_dutycycle(40, 1)


def test_pigpio_callback_sees_driven_edges_with_their_ticks_across_the_wrap(server: VirtualPigpiod, pi: Any) -> None:
    seen: list[tuple[int, int, int]] = []
    # GPIO 10 is pulled down from power-on, as the client's notion of the levels assumes since it connected.
    callback = pi.callback(10, pigpio.EITHER_EDGE, lambda gpio, level, tick: seen.append((gpio, level, tick)))
    ticks = [(1 << 32) - 20, (1 << 32) - 10, 5, 15]  # the last two after the wrap
    server.drive_edges(10, ticks, [1, 0, 1, 0])
    wait_until(lambda: len(seen) == 4)
    callback.cancel()
    assert seen == [(10, 1, ticks[0]), (10, 0, ticks[1]), (10, 1, ticks[2]), (10, 0, ticks[3])]


def test_pigpio_callback_only_sees_its_own_pin(server: VirtualPigpiod, pi: Any) -> None:
    seen: list[int] = []
    callback = pi.callback(22, pigpio.RISING_EDGE, lambda gpio, level, tick: seen.append(tick))
    start = server.tick()
    server.drive_edges(27, [start + 1, start + 2], [1, 0])
    server.drive_edges(22, [start + 3, start + 4, start + 5], [1, 0, 1])
    wait_until(lambda: len(seen) == 2)
    callback.cancel()
    assert seen == [(start + 3) & 0xFFFFFFFF, (start + 5) & 0xFFFFFFFF]


def test_glitch_filter_drops_short_pulses_and_stamps_steady_edges_late(server: VirtualPigpiod, pi: Any) -> None:
    seen: list[tuple[int, int]] = []
    pi.set_glitch_filter(9, 100)
    assert server.glitch_filter_us(9) == 100
    callback = pi.callback(9, pigpio.EITHER_EDGE, lambda gpio, level, tick: seen.append((level, tick)))
    t = 1_000_000
    server.drive_edges(9, [t, t + 30, t + 200, t + 1000, t + 1050, t + 2000], [1, 0, 1, 0, 1, 0])
    wait_until(lambda: len(seen) == 2)
    callback.cancel()
    # The 30 us pulse is gone, so is the 50 us dip at t+1000; the rises and falls that held are stamped 100 us late.
    assert seen == [(1, t + 300), (0, t + 2100)]


def test_gpiozero_pwm_duty_is_what_the_server_reports(server: VirtualPigpiod, factory: Any) -> None:
    motor = PWMOutputDevice(12, frequency=1000, pin_factory=factory)
    assert server.pwm_frequency(12) == 1000
    for duty in (0.0, 0.37, 1.0, 0.05):
        motor.value = duty
        assert server.pwm_duty(12) == pytest.approx(duty)
        assert motor.value == pytest.approx(duty)
    motor.close()
    assert server.pwm_duty(12) == 0.0
    assert server.mode(12) == pigpio.INPUT  # gpiozero hands its pins back as inputs


def test_gpiozero_digital_output_and_input(server: VirtualPigpiod, factory: Any) -> None:
    output = DigitalOutputDevice(16, pin_factory=factory)
    output.on()
    assert (server.mode(16), server.level(16)) == (pigpio.OUTPUT, 1)
    output.off()
    assert server.level(16) == 0
    sensor = DigitalInputDevice(20, pull_up=False, pin_factory=factory)
    changed = threading.Event()
    sensor.when_activated = changed.set
    server.drive_edges(20, [server.tick()], [1])
    assert changed.wait(2.0)
    assert sensor.value == 1
    output.close()
    sensor.close()


def _command(sock: socket.socket, cmd: int, p1: int = 0, p2: int = 0) -> int:
    sock.sendall(encode_command(cmd, p1, p2))
    return decode_result(sock.recv(COMMAND.size, socket.MSG_WAITALL))


def test_lost_reports_leave_a_gap_in_the_sequence(server: VirtualPigpiod) -> None:
    with (
        socket.create_connection(("127.0.0.1", server.port)) as control,
        socket.create_connection(("127.0.0.1", server.port)) as stream,
    ):
        handle = _command(stream, Cmd.NOIB)
        assert handle >= 0
        assert _command(control, Cmd.NB, handle, 1 << 21) == 0
        server.drive_edges(21, [10, 20, 30], [1, 0, 1])
        server.lose_reports(2)
        server.drive_edges(21, [40, 50, 60], [0, 1, 0])
        data = b""
        while len(data) < 4 * REPORT_SIZE:
            data += stream.recv(4096)
        reports = decode_reports(data)
        assert reports["seq"].tolist() == [0, 1, 2, 5]
        assert reports["tick"].tolist() == [10, 20, 30, 60]
        assert (reports["level"] >> 21 & 1).tolist() == [1, 0, 1, 0]
        assert _command(control, Cmd.NC, handle) == 0
        assert stream.recv(4096) == b""  # closing the handle closes its socket


def test_unknown_commands_and_corrupt_streams_get_clear_answers(server: VirtualPigpiod) -> None:
    with socket.create_connection(("127.0.0.1", server.port)) as sock:
        assert _command(sock, 56) == pigpio.PI_UNKNOWN_COMMAND  # I2C is not modelled
        assert _command(sock, Cmd.NB, 31, 1) == pigpio.PI_BAD_HANDLE
        sock.sendall(struct.pack("<IIII", Cmd.WRITE, 1, 0, 1 << 30))  # announces a gigabyte of extension
        assert sock.recv(16) == b""  # the server hangs up rather than wait for it
    with socket.create_connection(("127.0.0.1", server.port)) as sock:
        assert _command(sock, Cmd.HWVER) == PI4B_4GB  # and still serves others


async def test_serves_on_a_running_loop_too() -> None:
    async with VirtualPigpiod() as server:
        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        writer.write(encode_command(Cmd.WRITE, 25, 1))
        answer = await reader.readexactly(COMMAND.size)
        assert decode_result(answer) == 0
        assert server.level(25) == 1
        writer.close()
        await writer.wait_closed()


def test_drive_levels_only_moves_input_pins_of_the_mask(server: VirtualPigpiod, pi: Any) -> None:
    pi.write(26, 1)
    pi.set_mode(19, pigpio.INPUT)
    server.drive_levels(np.array([1, 2], dtype=np.uint32), np.array([0, 0], dtype=np.uint32), (1 << 26) | (1 << 19))
    assert server.level(26) == 1  # an output belongs to the client
    assert server.level(19) == 0


def test_robotd_vpigpiod_serves_alone_until_sigterm() -> None:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    process = python_child(["-m", "robotd", "vpigpiod", "--port", str(port)])
    try:
        assert process.stdout is not None
        assert f"127.0.0.1:{port}" in process.stdout.readline()
        client = pigpio.pi("127.0.0.1", port, show_errors=False)
        assert client.get_hardware_revision() == PI4B_4GB
        stop_pigpio_client(client)
        process.send_signal(signal.SIGTERM)
        process.communicate(timeout=10)
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
    assert process.returncode == 0
