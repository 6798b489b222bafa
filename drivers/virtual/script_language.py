"""pigpio's script language as pigpiod's PROC reads it: text in, a program or pigpio's error code out.

Sans-I/O. Facts from pigpio's documentation (the "Scripts" section of pigs) and its command parser:
- A script is words separated by white space: a command name in any case, then its operands. A number is a C
  integer (decimal, 0x hex, octal after a leading 0, optional sign) kept as 32 bits; `p0`..`p9` name the parameters,
  `v0`..`v149` the variables (lower case only, as pigpiod's scanner reads them).
- Each command has an operand shape (`Shape`); a bare number where a register belongs names a variable.
- `TAG L` names the position of the next instruction; JMP, JZ, JNZ, JM, JP and CALL jump to a tag. A repeated tag is
  PI_DUP_TAG, a 51st tag PI_TOO_MANY_TAGS, a jump to no tag PI_BAD_TAG; an unknown command, one not allowed in a
  script or bad operands is PI_BAD_SCRIPT_CMD. The first error in the text is the answer (PI_BAD_TAG last), and
  nothing is stored.

Modelled: the script-only instructions ADD AND CALL CMP DCR DCRA DIV HALT INR INRA JM JMP JNZ JP JZ LD LDA MLT MOD
NOP OR POP POPA PUSH PUSHA RET RL RLA RR RRA STA SUB TAG X XA XOR, the delays MILS and MICS, and the pin commands
the virtual pigpiod models: BC1 BC2 BR1 BR2 BS1 BS2 FG GDC HWVER M/MODES MG/MODEG P/PWM PFG PFS PIGPV PRG PRRG PRS
PUD R/READ T/TICK W/WRITE. Anything else pigpiod would run in a script (WAIT, EVTWT, SYS, LDAB, STAB, waves, I2C,
SPI, serial, servo, watchdogs, ...) is refused with PI_BAD_SCRIPT_CMD, as pigpiod refuses a command it does not know.
Deviations: an operand is a whole word (pigpiod's scanner would read "12abc" as 12 then "abc"); a negative register
number is refused (pigpiod would index outside its arrays).
"""

from __future__ import annotations

import enum
import re
from dataclasses import dataclass

from drivers.pigpiod.protocol import Cmd, Err

MAX_TAGS = 50
MAX_VARIABLES = 150
MAX_PARAMS = 10
MODE_LETTERS = "RW540123"
"""M's mode letter: its position is pigpio's mode number (R input 0, W output 1, 5 ALT5 2, 4 ALT4 3, 0 ALT0 4...)."""
PULL_LETTERS = "ODU"
"""PUD's pull letter: off 0, down 1, up 2."""


class Shape(enum.Enum):
    """The operands a command takes (pigpiod's verification types)."""

    NONE = "none"
    ANY = "x"  # one value, any sign
    POSITIVE = "u"  # one value >= 0
    REGISTER = "r"  # one parameter or variable
    TAG = "L"  # one tag number
    TWO_POSITIVE = "u u"
    REGISTER_ANY = "r x"
    TWO_REGISTERS = "r r"
    GPIO_MODE = "u mode-letter"
    GPIO_PULL = "u pull-letter"


class Kind(enum.IntEnum):
    """What an operand names (pigpiod's numbering)."""

    NUMBER = 1
    VARIABLE = 2
    PARAMETER = 3


@dataclass(frozen=True, slots=True)
class Operand:
    """A number, or the index of a variable or parameter."""

    kind: Kind
    value: int


@dataclass(frozen=True, slots=True)
class Instruction:
    """One parsed command: its canonical name, its socket command number if pigpiod runs it as one, its operands.

    A jump's operand is the index of the instruction its tag names.
    """

    name: str
    cmd: int | None
    operands: tuple[Operand, ...]


@dataclass(frozen=True, slots=True)
class Program:
    """A stored script's instructions (tags resolved and removed)."""

    instructions: tuple[Instruction, ...]


class ScriptError(Exception):
    """A script pigpiod would refuse; `code` is its error code."""

    def __init__(self, code: int, reason: str) -> None:
        super().__init__(f"{reason} ({Err(code).name})")
        self.code = code


_SCRIPT_ONLY: dict[str, Shape] = {
    **dict.fromkeys(("DCRA", "HALT", "INRA", "NOP", "POPA", "PUSHA", "RET"), Shape.NONE),
    **dict.fromkeys(("ADD", "AND", "CMP", "DIV", "LDA", "MLT", "MOD", "OR", "RLA", "RRA", "SUB", "XOR"), Shape.ANY),
    **dict.fromkeys(("DCR", "INR", "POP", "PUSH", "STA", "XA"), Shape.REGISTER),
    **dict.fromkeys(("CALL", "JM", "JMP", "JNZ", "JP", "JZ", "TAG"), Shape.TAG),
    **dict.fromkeys(("LD", "RL", "RR"), Shape.REGISTER_ANY),
    "X": Shape.TWO_REGISTERS,
}
JUMPS = frozenset({"CALL", "JM", "JMP", "JNZ", "JP", "JZ"})

_SOCKET_COMMANDS: dict[str, tuple[Cmd, Shape]] = {
    "BC1": (Cmd.BC1, Shape.ANY),
    "BC2": (Cmd.BC2, Shape.ANY),
    "BS1": (Cmd.BS1, Shape.ANY),
    "BS2": (Cmd.BS2, Shape.ANY),
    "BR1": (Cmd.BR1, Shape.NONE),
    "BR2": (Cmd.BR2, Shape.NONE),
    "HWVER": (Cmd.HWVER, Shape.NONE),
    "PIGPV": (Cmd.PIGPV, Shape.NONE),
    "TICK": (Cmd.TICK, Shape.NONE),
    "MILS": (Cmd.MILS, Shape.POSITIVE),
    "MICS": (Cmd.MICS, Shape.POSITIVE),
    "READ": (Cmd.READ, Shape.POSITIVE),
    "MODEG": (Cmd.MODEG, Shape.POSITIVE),
    "GDC": (Cmd.GDC, Shape.POSITIVE),
    "PRG": (Cmd.PRG, Shape.POSITIVE),
    "PFG": (Cmd.PFG, Shape.POSITIVE),
    "PRRG": (Cmd.PRRG, Shape.POSITIVE),
    "WRITE": (Cmd.WRITE, Shape.TWO_POSITIVE),
    "PWM": (Cmd.PWM, Shape.TWO_POSITIVE),
    "PRS": (Cmd.PRS, Shape.TWO_POSITIVE),
    "PFS": (Cmd.PFS, Shape.TWO_POSITIVE),
    "FG": (Cmd.FG, Shape.TWO_POSITIVE),
    "MODES": (Cmd.MODES, Shape.GPIO_MODE),
    "PUD": (Cmd.PUD, Shape.GPIO_PULL),
}
_ALIASES = {"W": "WRITE", "P": "PWM", "R": "READ", "M": "MODES", "MG": "MODEG", "T": "TICK"}

_NUMBER = re.compile(r"[+-]?(?:0[xX][0-9a-fA-F]+|0[0-7]*|[1-9][0-9]*)")


def int32(value: int) -> int:
    """`value` as a C int holds it: the low 32 bits, signed."""
    value &= 0xFFFFFFFF
    return value - (1 << 32) if value & 0x80000000 else value


def _c_integer(word: str) -> int | None:
    """A word read as C's %i reads it, or None."""
    if not _NUMBER.fullmatch(word):
        return None
    sign = -1 if word[0] == "-" else 1
    digits = word.lstrip("+-")
    base = 16 if digits[:2] in ("0x", "0X") else 8 if len(digits) > 1 and digits[0] == "0" else 10
    return int32(sign * int(digits, base))


def _operand(word: str | None) -> Operand | None:
    """A number, `vN` or `pN`; None when the word is none of them or names a register that does not exist."""
    if word is None:
        return None
    number = _c_integer(word)
    if number is not None:
        return Operand(Kind.NUMBER, number)
    if word[:1] in ("v", "p"):
        index = _c_integer(word[1:])
        limit = MAX_VARIABLES if word[0] == "v" else MAX_PARAMS
        if index is not None and 0 <= index < limit:
            return Operand(Kind.VARIABLE if word[0] == "v" else Kind.PARAMETER, index)
    return None


def _register(operand: Operand | None) -> bool:
    return operand is not None and 0 <= operand.value < MAX_VARIABLES


def _positive(operand: Operand | None) -> bool:
    return operand is not None and operand.value >= 0


def _letter(word: str | None, letters: str) -> Operand | None:
    if word is None or len(word) != 1 or word.upper() not in letters:
        return None
    return Operand(Kind.NUMBER, letters.index(word.upper()))


def _operands(shape: Shape, words: list[str], at: int) -> tuple[Operand, ...] | None:
    """The operands of `shape` starting at `words[at]`, or None when they are missing or invalid."""
    first = words[at] if at < len(words) else None
    second = words[at + 1] if at + 1 < len(words) else None
    one, two = _operand(first), _operand(second)
    checks: dict[Shape, tuple[tuple[Operand | None, ...], bool]] = {
        Shape.NONE: ((), True),
        Shape.ANY: ((one,), one is not None),
        Shape.POSITIVE: ((one,), _positive(one)),
        Shape.REGISTER: ((one,), _register(one)),
        Shape.TAG: ((one,), one is not None and one.kind == Kind.NUMBER),
        Shape.TWO_POSITIVE: ((one, two), _positive(one) and _positive(two)),
        Shape.REGISTER_ANY: ((one, two), _register(one) and two is not None),
        Shape.TWO_REGISTERS: ((one, two), _register(one) and _register(two)),
    }
    operands: tuple[Operand | None, ...]
    if shape in (Shape.GPIO_MODE, Shape.GPIO_PULL):
        letter = _letter(second, MODE_LETTERS if shape == Shape.GPIO_MODE else PULL_LETTERS)
        operands, valid = (one, letter), _positive(one) and letter is not None
    else:
        operands, valid = checks[shape]
    if not valid:
        return None
    return tuple(operand for operand in operands if operand is not None)


def parse(text: str) -> Program:
    """Parse a script as pigpiod's PROC does, or raise ScriptError with the code pigpiod would answer."""
    words = text.split("\0", 1)[0].split()  # pigpiod reads the text as a C string
    instructions: list[Instruction] = []
    tags: dict[int, int] = {}
    first_error: ScriptError | None = None
    at = 0
    while at < len(words):
        word = words[at]
        at += 1
        name = _ALIASES.get(word.upper(), word.upper())
        if name in _SCRIPT_ONLY:
            cmd, shape = None, _SCRIPT_ONLY[name]
        elif name in _SOCKET_COMMANDS:
            cmd, shape = _SOCKET_COMMANDS[name]
        else:
            first_error = first_error or ScriptError(Err.BAD_SCRIPT_CMD, f"unknown or unmodelled command {word!r}")
            continue
        operands = _operands(shape, words, at)
        if operands is None:
            # pigpiod consumes no word it could not read: the next one is read as a command
            first_error = first_error or ScriptError(Err.BAD_SCRIPT_CMD, f"bad operands to {word!r}")
            continue
        at += len(operands)
        if name != "TAG":
            instructions.append(Instruction(name, int(cmd) if cmd is not None else None, operands))
            continue
        tag = operands[0].value
        if len(tags) >= MAX_TAGS:
            first_error = first_error or ScriptError(Err.TOO_MANY_TAGS, f"more than {MAX_TAGS} tags")
        elif tag in tags:
            first_error = first_error or ScriptError(Err.DUP_TAG, f"tag {tag} appears twice")
        else:
            tags[tag] = len(instructions)
    if first_error is not None:
        raise first_error
    resolved = []
    for instruction in instructions:
        if instruction.name in JUMPS:
            tag = instruction.operands[0].value
            if tag not in tags:
                raise ScriptError(Err.BAD_TAG, f"{instruction.name} to tag {tag}, which does not exist")
            instruction = Instruction(instruction.name, None, (Operand(Kind.NUMBER, tags[tag]),))  # noqa: PLW2901
        resolved.append(instruction)
    return Program(tuple(resolved))
