"""The script parser alone: words to instructions, tags to positions, numbers and registers as pigpiod reads them."""

from __future__ import annotations

import pytest

from drivers.pigpiod.protocol import Cmd, Err
from drivers.virtual.script_language import Kind, Operand, ScriptError, parse


def test_tags_become_the_positions_of_the_instructions_they_name() -> None:
    program = parse("tag 7 ld v0 3 tag 8\n dcr v0\tjnz 8 jmp 7 TAG 9")
    names = [(i.name, i.operands) for i in program.instructions]
    assert names == [
        ("LD", (Operand(Kind.VARIABLE, 0), Operand(Kind.NUMBER, 3))),
        ("DCR", (Operand(Kind.VARIABLE, 0),)),
        ("JNZ", (Operand(Kind.NUMBER, 1),)),
        ("JMP", (Operand(Kind.NUMBER, 0),)),
    ]


def test_numbers_are_c_integers_and_registers_are_named_or_bare() -> None:
    program = parse("lda 0x1F lda 017 lda -3 lda +4 lda p9 lda v149 inr 12 lda 0xFFFFFFFF")
    assert [i.operands[0] for i in program.instructions] == [
        Operand(Kind.NUMBER, 31),
        Operand(Kind.NUMBER, 15),
        Operand(Kind.NUMBER, -3),
        Operand(Kind.NUMBER, 4),
        Operand(Kind.PARAMETER, 9),
        Operand(Kind.VARIABLE, 149),
        Operand(Kind.NUMBER, 12),  # a bare register number: variable 12 when run
        Operand(Kind.NUMBER, -1),  # 32 bits
    ]


def test_short_names_and_letters_become_the_socket_commands() -> None:
    program = parse("w 4 1 p 18 9 r 4 m 4 W mg 4 t pud 4 u")
    commands = [(i.cmd, tuple(o.value for o in i.operands)) for i in program.instructions]
    assert commands == [
        (Cmd.WRITE, (4, 1)),
        (Cmd.PWM, (18, 9)),
        (Cmd.READ, (4,)),
        (Cmd.MODES, (4, 1)),
        (Cmd.MODEG, (4,)),
        (Cmd.TICK, ()),
        (Cmd.PUD, (4, 2)),
    ]


def test_the_first_error_in_the_text_is_the_answer() -> None:
    with pytest.raises(ScriptError) as refused:
        parse("tag 1 tag 1 wait 4 jmp 3")
    assert refused.value.code == Err.DUP_TAG
    with pytest.raises(ScriptError) as refused:
        parse("wait 4 tag 1 tag 1")
    assert refused.value.code == Err.BAD_SCRIPT_CMD


def test_a_script_ends_at_a_nul_as_pigpiods_c_string_does() -> None:
    assert len(parse("halt\0bogus").instructions) == 1
