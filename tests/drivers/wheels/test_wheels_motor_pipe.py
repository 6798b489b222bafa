"""Motor writes never wait for pigpiod: a stalled pigpiod is reported, it does not stall the caller."""

from __future__ import annotations

import socket
import threading

import pytest
from wheels_support import wait_until

from drivers.pigpiod.client import CommandPipe, PigpioCommandError
from drivers.pigpiod.protocol import Cmd
from drivers.virtual.pigpiod import VirtualPigpiod

PERIOD_OF_WRITES = [(Cmd.PWM, 12, 100), (Cmd.BC1, 1 << 5 | 1 << 6, 0), (Cmd.BS1, 1 << 5, 0), (Cmd.PWM, 13, 80)]


def test_a_pigpiod_that_stops_answering_is_reported_stalled_without_blocking() -> None:
    # A pigpiod that accepts the connection and then neither reads nor answers anything: SIGSTOPped, or hung.
    with socket.create_server(("127.0.0.1", 0)) as stalled:
        pipe = CommandPipe("127.0.0.1", stalled.getsockname()[1], 2.0)
        accepted, _ = stalled.accept()
        sends = 0
        error: ConnectionError | None = None
        for _ in range(100_000):  # a blocking write would hang here once the kernel's buffers are full
            try:
                pipe.send(PERIOD_OF_WRITES)
            except ConnectionError as refused:
                error = refused
                break
            sends += 1
        assert error is not None
        assert "stalled" in str(error)
        assert pipe.broken
        assert sends * len(PERIOD_OF_WRITES) <= CommandPipe.MAX_OWED + len(PERIOD_OF_WRITES)
        with pytest.raises(ConnectionError):
            pipe.send(PERIOD_OF_WRITES)  # nothing more is sent on a broken pipe
        pipe.close()
        accepted.close()


def test_commands_are_carried_out_in_order_and_a_refusal_is_reported_at_the_next_send(
    server: VirtualPigpiod,
) -> None:
    pipe = CommandPipe("127.0.0.1", server.port, 2.0)
    try:
        pipe.send([(Cmd.MODES, 12, 1), (Cmd.PWM, 12, 255), (Cmd.PWM, 12, 64)])
        wait_until(lambda: server.pwm_duty(12) == 64 / 255)
        # no such GPIO: refused, and said at a later call (send collects first); the answer after it is not lost
        pipe.send([(Cmd.PWM, 99, 10), (Cmd.PWM, 12, 32)])

        refusals: list[str] = []

        def refused() -> bool:
            try:
                pipe.collect()
            except PigpioCommandError as error:
                refusals.append(str(error))
            return bool(refusals)

        wait_until(refused)
        assert "PWM(99, 10)" in refusals[0]
        assert pipe.owed == 0  # both answers counted off: a refusal does not leave them owed for ever
    finally:
        pipe.close()


def test_a_send_returns_before_pigpiod_answers() -> None:
    # pigpiod reads the commands but answers only when told: the sender has long returned by then.
    with socket.create_server(("127.0.0.1", 0)) as slow:
        pipe = CommandPipe("127.0.0.1", slow.getsockname()[1], 2.0)
        accepted, _ = slow.accept()
        answer = threading.Event()

        def pigpiod() -> None:
            data = b""
            while len(data) < 16 * len(PERIOD_OF_WRITES):
                data += accepted.recv(1024)
            answer.wait(5.0)
            accepted.sendall(data)  # pigpiod echoes cmd, p1, p2 and puts the result (0 here: p3 was 0) last

        thread = threading.Thread(target=pigpiod)
        thread.start()
        pipe.send(PERIOD_OF_WRITES)
        assert pipe.owed == len(PERIOD_OF_WRITES)  # returned without an answer
        answer.set()
        assert pipe.flush(5.0)
        assert pipe.owed == 0
        thread.join()
        pipe.close()
        accepted.close()
