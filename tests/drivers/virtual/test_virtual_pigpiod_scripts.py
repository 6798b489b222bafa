"""pigpio scripts on the virtual pigpiod, through the real `pigpio` client: storing, running, parameters, status,
stopping and deleting, the language's semantics on hand-written scripts, and what the store refuses."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import pigpio
import pytest

from drivers.pigpiod.protocol import Err, Mode
from drivers.virtual.pigpiod import VirtualPigpiod


def wait_until(condition: Callable[[], bool], timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError("condition not reached in time")
        time.sleep(0.002)


def halted(pi: Any, script_id: int) -> bool:
    return bool(pi.script_status(script_id)[0] == pigpio.PI_SCRIPT_HALTED)


def run_to_end(pi: Any, text: str, params: list[int] | None = None) -> tuple[int, ...]:
    """Store, run until the script halts, delete; the parameters it left."""
    script_id = pi.store_script(text.encode())
    wait_until(lambda: halted(pi, script_id))
    pi.run_script(script_id, params)
    wait_until(lambda: halted(pi, script_id))
    left: tuple[int, ...] = pi.script_status(script_id)[1]
    pi.delete_script(script_id)
    return left


# --- the socket commands ------------------------------------------------------------------------------------------


def test_the_pigpio_client_stores_runs_updates_reads_and_deletes_a_script(pi: Any) -> None:
    # Copies p0 into p2 every 5 ms until p0 is zero, then sets p3 and ends.
    script_id = pi.store_script(b"tag 0 mils 5 lda p0 sta p2 cmp 0 jnz 0 ld p3 1")
    assert script_id == 0
    wait_until(lambda: halted(pi, script_id))
    assert pi.run_script(script_id, [7]) == 0
    assert pi.script_status(script_id)[0] == pigpio.PI_SCRIPT_RUNNING
    wait_until(lambda: pi.script_status(script_id)[1][2] == 7)
    assert pi.update_script(script_id, [9]) == 0
    wait_until(lambda: pi.script_status(script_id)[1][2] == 9)
    assert pi.update_script(script_id, [0]) == 0
    wait_until(lambda: halted(pi, script_id))
    assert pi.script_status(script_id)[1][:4] == (0, 0, 0, 1)
    assert pi.delete_script(script_id) == 0
    assert pi.script_status(script_id)[0] == Err.BAD_SCRIPT_ID
    assert pi.store_script(b"halt") == 0, "the slot of a deleted script is free again"


def test_run_while_running_is_refused_and_a_stop_lets_the_running_delay_finish(
    pi: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(pigpio, "exceptions", False)
    script_id = pi.store_script(b"tag 0 mils 1500 jmp 0")
    wait_until(lambda: halted(pi, script_id))
    started = time.monotonic()
    assert pi.run_script(script_id) == 0
    assert pi.run_script(script_id) == Err.NOT_HALTED
    assert pi.stop_script(script_id) == 0
    assert pi.script_status(script_id)[0] == pigpio.PI_SCRIPT_RUNNING, "pigpiod finishes the MILS before halting"
    assert pi.delete_script(script_id) == 0  # answered once the script has halted
    assert time.monotonic() - started >= 1.4
    assert pi.script_status(script_id)[0] == Err.BAD_SCRIPT_ID


def test_parameters_set_by_run_and_update_are_the_first_ones_only(pi: Any) -> None:
    script_id = pi.store_script(b"halt")
    wait_until(lambda: halted(pi, script_id))
    pi.run_script(script_id, [1, 2, 3, 4, 5, 6, 7, 8, 9, 10])
    wait_until(lambda: halted(pi, script_id))
    pi.update_script(script_id, [0xFFFFFFFF, 0x7FFFFFFF])  # the client sends words; a script sees C ints
    assert pi.script_status(script_id)[1] == (-1, 0x7FFFFFFF, 3, 4, 5, 6, 7, 8, 9, 10)
    with pytest.raises(pigpio.error, match="too many script parameters"):
        pi.update_script(script_id, list(range(11)))


def test_pigpiod_holds_32_scripts(pi: Any) -> None:
    ids = [pi.store_script(b"halt") for _ in range(32)]
    assert ids == list(range(32))
    with pytest.raises(pigpio.error, match="no more room for scripts"):
        pi.store_script(b"halt")
    for script_id in ids:
        pi.delete_script(script_id)


@pytest.mark.parametrize(
    ("text", "code"),
    [
        ("wait 0x10", Err.BAD_SCRIPT_CMD),  # pigpiod runs it; not modelled here
        ("sys myscript", Err.BAD_SCRIPT_CMD),
        ("wvclr", Err.BAD_SCRIPT_CMD),
        ("servo 4 1500", Err.BAD_SCRIPT_CMD),
        ("bogus 1", Err.BAD_SCRIPT_CMD),
        ("proc w 4 1", Err.BAD_SCRIPT_CMD),  # not allowed in a script
        ("w 4", Err.BAD_SCRIPT_CMD),  # an operand missing
        ("w -1 0", Err.BAD_SCRIPT_CMD),  # a GPIO must not be negative
        ("ld p10 1", Err.BAD_SCRIPT_CMD),
        ("inr v150", Err.BAD_SCRIPT_CMD),
        ("lda V1", Err.BAD_SCRIPT_CMD),  # registers are lower case
        ("jmp v1", Err.BAD_SCRIPT_CMD),  # a tag is a number
        ("m 4 q", Err.BAD_SCRIPT_CMD),
        ("tag 1 w 4 1 tag 1", Err.DUP_TAG),
        ("jmp 5", Err.BAD_TAG),
        ("jmp 9 tag 2 tag 2", Err.DUP_TAG),  # the duplicate is found before the unresolved jump
        (" ".join(f"tag {n}" for n in range(51)), Err.TOO_MANY_TAGS),
    ],
)
def test_the_store_refuses_what_pigpiod_refuses_with_its_error_code(
    pi: Any, monkeypatch: pytest.MonkeyPatch, text: str, code: int
) -> None:
    monkeypatch.setattr(pigpio, "exceptions", False)
    assert pi.store_script(text.encode()) == code
    assert pi.store_script(b"halt") == 0, "a refused script takes no slot"


def test_commands_that_pigpiod_accepts_in_scripts_are_stored(pi: Any) -> None:
    text = "M 4 w PUD 4 d MODES 5 R pud 5 U Write 4 1 p 18 100 prs 18 200 pfs 18 800 bs1 0x10 bc1 16 br1 t nop"
    assert pi.store_script(text.encode()) == 0


# --- the language, on hand-written scripts -------------------------------------------------------------------------


def test_a_counted_loop_runs_its_body_the_given_number_of_times(pi: Any) -> None:
    left = run_to_end(pi, "ld v0 p0 ld v1 0 tag 1 inr v1 dcr v0 jnz 1 lda v1 sta p1", [10])
    assert left[1] == 10


def test_arithmetic_is_32_bit_c_arithmetic(pi: Any) -> None:
    script = (
        "lda 7 add 5 sta p0 "
        "lda 7 sub 10 sta p1 "
        "lda -7 div 2 sta p2 "  # C truncates toward zero
        "lda -7 mod 2 sta p3 "  # and the remainder takes the dividend's sign
        "lda 3 mlt -4 sta p4 "
        "lda 0x0f and 6 or 0100 xor 1 sta p5 "  # 0100 is octal 64
        "lda 1 rla 4 sta p6 "
        "lda -16 rra 2 sta p7 "  # an arithmetic shift
        "lda 0x7fffffff inra sta p8 "  # wraps
        "lda 0 dcra sta p9"
    )
    assert run_to_end(pi, script) == (12, -3, -3, -1, -12, 71, 16, -4, -(1 << 31), -1)


@pytest.mark.parametrize(("p0", "sign"), [(-5, -1), (0, 0), (9, 1)])
def test_compare_and_conditional_jumps_pick_the_branch(pi: Any, p0: int, sign: int) -> None:
    script = "lda p0 cmp 0 jm 1 jz 2 jp 3 halt tag 1 ld p1 -1 halt tag 2 ld p1 0 halt tag 3 ld p1 1"
    assert run_to_end(pi, script, [p0 & 0xFFFFFFFF, 99])[1] == sign  # the client sends words


def test_registers_stack_and_subroutines(pi: Any) -> None:
    script = (
        "ld v0 1 ld v1 2 x v0 v1 "  # v0 = 2, v1 = 1
        "push v0 pop p1 "  # p1 = 2
        "lda 5 xa v1 sta p2 "  # v1 = 5, A = 1
        "lda v1 sta p3 "  # p3 = 5
        "call 9 ld p5 7 halt "
        "tag 9 ld p4 42 pusha popa rl p4 1 rr p4 2 ret"  # p4 = 42 << 1 >> 2 = 21
    )
    assert run_to_end(pi, script)[1:6] == (2, 1, 5, 21, 7)


def test_a_command_result_lands_in_the_accumulator(pi: Any, server: VirtualPigpiod) -> None:
    assert run_to_end(pi, "w 99 1 sta p1 w 17 1 r 17 sta p2 mg 17 sta p3")[1:4] == (Err.BAD_GPIO, 1, Mode.OUTPUT)


def test_a_failing_script_stops_there(pi: Any) -> None:
    assert run_to_end(pi, "ld p1 1 pop p2 ld p1 2")[1] == 1  # the pop has nothing to take
    assert run_to_end(pi, "ld p1 1 lda 1 div 0 ld p1 2")[1] == 1


def test_variables_persist_between_runs_and_the_accumulator_does_not(pi: Any) -> None:
    script_id = pi.store_script(b"inr v0 lda v0 sta p1 inra sta p2")
    for _ in range(2):
        wait_until(lambda: halted(pi, script_id))
        pi.run_script(script_id)
    wait_until(lambda: halted(pi, script_id))
    assert pi.script_status(script_id)[1][1:3] == (2, 3)


def test_mils_waits_real_milliseconds(pi: Any) -> None:
    script_id = pi.store_script(b"mils 200 ld p1 1")
    wait_until(lambda: halted(pi, script_id))
    started = time.monotonic()
    pi.run_script(script_id)
    wait_until(lambda: pi.script_status(script_id)[1][1] == 1)
    assert time.monotonic() - started >= 0.2


def test_a_script_that_never_sleeps_leaves_the_server_answering(pi: Any) -> None:
    script_id = pi.store_script(b"tag 0 inr v0 jmp 0")
    wait_until(lambda: halted(pi, script_id))
    pi.run_script(script_id)
    for _ in range(20):
        assert pi.get_hardware_revision() > 0
    pi.stop_script(script_id)
    wait_until(lambda: halted(pi, script_id))


def test_script_writes_reach_the_pins_and_the_history_names_the_script(pi: Any, server: VirtualPigpiod) -> None:
    pi.write(17, 0)
    server.clear_pin_history()
    run_to_end(pi, "w 17 1 p 18 64 w 17 0 m 22 w bs1 0x400000")
    assert server.level(17) == 0
    assert server.level(22) == 1
    assert server.pwm_duty(18) == pytest.approx(64 / 255)
    writes = [(w.source, w.command, w.gpio, w.level) for w in server.pin_history()]
    assert writes == [
        ("script 0", "WRITE", 17, 1),
        ("script 0", "PWM", 18, 0),
        ("script 0", "WRITE", 17, 0),
        ("script 0", "MODES", 22, 0),
        ("script 0", "BS1", 22, 1),
    ]
