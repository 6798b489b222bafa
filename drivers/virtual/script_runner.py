"""Scripts stored in the virtual pigpiod: PROC, PROCR, PROCU, PROCP, PROCS, PROCD, and the machine that runs them.

Theory of operation (facts from pigpio's script documentation and its library): pigpiod holds up to 32 scripts,
numbered from 0 (lowest free first). A stored script is INITING until its thread is up, then HALTED; PROCR sets the
first parameters it is given and runs it from the top with the accumulator A, the flags F and the program counter
zeroed (parameters and variables keep their values between runs; all start at 0). A pin command or a delay sets A and
F to its result. The script runs until it passes its last instruction, executes HALT, fails (stack over- or
underflow), or is asked to stop: PROCS takes effect between two instructions, so a MILS in progress finishes first,
and the status reads RUNNING until then; PROCD answers only once the script has halted. PROCU overwrites the first
parameters whatever the script is doing. PROCR on a script that is not HALTED is PI_NOT_HALTED.

Here each running script is a task on the virtual pigpiod's event loop, in real time: MILS and MICS sleep on the
loop's clock; instructions between two delays run without a pause, pausing every `YIELD_EVERY` instructions for
`BUSY_PAUSE_S` so a script that never sleeps cannot starve the sockets nor the other threads of the process. The pause
is a real sleep, not a bare yield: a loop that gives up the GIL only for an instant (select with no timeout) and takes
it straight back starves a thread waiting for it, since CPython forces a switch only when nobody released the GIL
for a whole switch interval (seen here: the test process's client thread waited 120 s for one answer). Pin commands
go through the same code as the socket's (`run_command`), labelled with the script's id for the pin history.

Not modelled: WAITING (WAIT and EVTWT are not modelled, see drivers.virtual.script_language); FAILED is never seen, as
pigpiod's script thread goes back to HALTED at once after a failure (the reason is kept in `failure`); DIV or MOD by
zero, which would crash pigpiod, fails the script instead; shift counts are taken modulo 32.
"""

from __future__ import annotations

import asyncio
import enum
from collections.abc import Callable
from dataclasses import dataclass, field

from drivers.pigpiod.protocol import (
    MAX_SCRIPT_PARAMS,
    MAX_SCRIPTS,
    SCRIPT_STATUS,
    Cmd,
    Command,
    Err,
    ScriptState,
    decode_params,
)
from drivers.virtual.script_language import (
    MAX_VARIABLES,
    Instruction,
    Kind,
    Operand,
    Program,
    ScriptError,
    int32,
    parse,
)

STACK_SIZE = 256
MAX_MILS = 60_000
MAX_MICS = 1_000_000
YIELD_EVERY = 1000
BUSY_PAUSE_S = 0.001  # a busy script keeps most of the loop's time, the sockets and other threads get theirs

RunCommand = Callable[[Command, str], int]
"""Runs one socket command for a script (the second argument names it for the pin history); returns the result."""


class _Request(enum.Enum):
    RUN = "run"
    HALT = "halt"


class ScriptFailedError(Exception):
    """The script cannot go on (its status becomes HALTED)."""


@dataclass(slots=True)
class StoredScript:
    """One slot of pigpiod's script table."""

    id: int
    program: Program
    params: list[int] = field(default_factory=lambda: [0] * MAX_SCRIPT_PARAMS)
    variables: list[int] = field(default_factory=lambda: [0] * MAX_VARIABLES)
    state: ScriptState = ScriptState.INITING
    request: _Request = _Request.HALT
    dying: bool = False
    task: asyncio.Task[None] | None = None
    failure: str | None = None
    runs: int = 0


class ScriptHost:
    """pigpiod's script table and its commands; every method runs on the server's event loop."""

    def __init__(self, run_command: RunCommand) -> None:
        self._run_command = run_command
        self.scripts: dict[int, StoredScript] = {}

    # --- the socket commands -----------------------------------------------------------------------------------

    def store(self, text: bytes) -> int:
        """PROC: parse and store a script; its id, or pigpio's error code."""
        slot = next((i for i in range(MAX_SCRIPTS) if i not in self.scripts), None)
        if slot is None:
            return Err.NO_SCRIPT_ROOM
        try:
            program = parse(text.decode("latin-1"))
        except ScriptError as error:
            return error.code
        script = StoredScript(slot, program)
        self.scripts[slot] = script
        asyncio.get_running_loop().call_soon(self._ready, script)  # pigpiod starts the script's thread
        return slot

    def run(self, script_id: int, extension: bytes) -> int:
        """PROCR: set the first parameters and run the script from its first instruction."""
        script, error = self._checked(script_id, extension)
        if script is None:
            return error
        if script.state != ScriptState.HALTED:
            return Err.NOT_HALTED
        self._set_params(script, extension)
        script.request, script.state, script.failure = _Request.RUN, ScriptState.RUNNING, None
        script.runs += 1
        script.task = asyncio.get_running_loop().create_task(self._execute(script), name=f"script {script.id}")
        return 0

    def update(self, script_id: int, extension: bytes) -> int:
        """PROCU: overwrite the first parameters, running or not."""
        script, error = self._checked(script_id, extension)
        if script is None:
            return error
        self._set_params(script, extension)
        return 0

    def status(self, script_id: int) -> tuple[int, bytes]:
        """PROCP: (byte count, run status and p0..p9), or (error code, nothing)."""
        script = self._live(script_id)
        if script is None:
            return Err.BAD_SCRIPT_ID, b""
        return SCRIPT_STATUS.size, SCRIPT_STATUS.pack(int(script.state), *script.params)

    def stop(self, script_id: int) -> int:
        """PROCS: ask the script to halt after its current instruction."""
        script = self._live(script_id)
        if script is None:
            return Err.BAD_SCRIPT_ID
        script.request = _Request.HALT
        return 0

    def delete(self, script_id: int) -> int | asyncio.Future[int]:
        """PROCD: halt and forget the script; answered once it has halted (a future while it finishes a delay)."""
        script = self._live(script_id)
        if script is None:
            return Err.BAD_SCRIPT_ID
        script.dying, script.request = True, _Request.HALT
        task = script.task
        if task is None or task.done():
            del self.scripts[script_id]
            return 0
        answer: asyncio.Future[int] = asyncio.get_running_loop().create_future()

        def forget(_task: asyncio.Task[None]) -> None:
            self.scripts.pop(script_id, None)
            if not answer.done():
                answer.set_result(0)

        task.add_done_callback(forget)
        return answer

    async def aclose(self) -> None:
        """Stop every script (the server is going away)."""
        tasks = [s.task for s in self.scripts.values() if s.task is not None and not s.task.done()]
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        self.scripts.clear()

    # --- bookkeeping -----------------------------------------------------------------------------------------------

    def _live(self, script_id: int) -> StoredScript | None:
        script = self.scripts.get(script_id)
        return None if script is None or script.dying else script

    def _checked(self, script_id: int, extension: bytes) -> tuple[StoredScript | None, int]:
        if script_id >= MAX_SCRIPTS:
            return None, Err.BAD_SCRIPT_ID
        if len(extension) // 4 > MAX_SCRIPT_PARAMS:
            return None, Err.TOO_MANY_PARAM
        script = self._live(script_id)
        return script, Err.BAD_SCRIPT_ID

    @staticmethod
    def _set_params(script: StoredScript, extension: bytes) -> None:
        values = decode_params(extension)
        script.params[: len(values)] = values

    @staticmethod
    def _ready(script: StoredScript) -> None:
        if script.state == ScriptState.INITING:
            script.state = ScriptState.HALTED

    # --- the virtual machine ---------------------------------------------------------------------------------------

    async def _execute(self, script: StoredScript) -> None:
        """Run the script until it ends, halts, fails or is asked to stop."""
        machine = _Machine(script, self._run_command)
        instructions = script.program.instructions
        since_yield = 0
        try:
            while script.request == _Request.RUN and machine.pc < len(instructions):
                delay_s = machine.step(instructions[machine.pc])
                since_yield += 1
                if delay_s is not None:
                    await asyncio.sleep(delay_s)
                    since_yield = 0
                elif since_yield >= YIELD_EVERY:
                    await asyncio.sleep(BUSY_PAUSE_S)
                    since_yield = 0
                if machine.halted:
                    break
        except ScriptFailedError as failure:
            script.failure = str(failure)
        finally:
            script.state = ScriptState.HALTED


class _Machine:
    """The accumulator, flags, program counter and stack of one run of a script."""

    def __init__(self, script: StoredScript, run_command: RunCommand) -> None:
        self.script = script
        self.run_command = run_command
        self.source = f"script {script.id}"
        self.a = self.f = self.pc = 0
        self.stack: list[int] = []
        self.halted = False

    def value(self, operand: Operand) -> int:
        """An operand's value: a number, or the content of the register it names."""
        if operand.kind == Kind.PARAMETER:
            return self.script.params[operand.value]
        if operand.kind == Kind.VARIABLE:
            return self.script.variables[operand.value]
        return operand.value

    def _registers(self, operand: Operand) -> list[int]:
        """The array a register operand lives in (a bare number names a variable)."""
        return self.script.params if operand.kind == Kind.PARAMETER else self.script.variables

    def _store(self, operand: Operand, value: int) -> int:
        self._registers(operand)[operand.value] = int32(value)
        return int32(value)

    def _push(self, value: int) -> None:
        if len(self.stack) >= STACK_SIZE:
            raise ScriptFailedError("too many pushes")
        self.stack.append(value)

    def _pop(self) -> int:
        if not self.stack:
            raise ScriptFailedError("too many pops")
        return self.stack.pop()

    def step(self, instruction: Instruction) -> float | None:
        """Execute one instruction; returns the seconds to sleep for a delay, else None."""
        if instruction.cmd is not None:
            return self._command(instruction)
        name, operands = instruction.name, instruction.operands
        x = self.value(operands[-1]) if operands else 0
        self.pc += 1
        if name in _ARITHMETIC:
            self.a = self.f = int32(_ARITHMETIC[name](self.a, x))
        elif name in _CONDITIONS:
            if _CONDITIONS[name](self.f):
                self.pc = x
        elif name in _REGISTER_OPS:
            self.f = self._store(operands[0], _REGISTER_OPS[name](self.value(operands[0]), x))
        else:
            self._other(name, operands, x)
        return None

    def _other(self, name: str, operands: tuple[Operand, ...], x: int) -> None:
        match name:
            case "CMP":
                self.f = int32(self.a - x)
            case "LD":
                self._store(operands[0], x)
            case "LDA":
                self.a = x
            case "STA":
                self._store(operands[0], self.a)
            case "DIV" | "MOD":
                if x == 0:
                    raise ScriptFailedError(f"{name} by zero")
                quotient = abs(self.a) // abs(x) * (1 if (self.a < 0) == (x < 0) else -1)  # C truncates
                self.a = self.f = int32(quotient if name == "DIV" else self.a - quotient * x)
            case "HALT":
                self.pc -= 1
                self.halted = True
            case "CALL":
                self._push(self.pc)
                self.pc = x
            case "RET":
                self.pc = self._pop()
            case "PUSH":
                self._push(self.value(operands[0]))
            case "PUSHA":
                self._push(self.a)
            case "POP":
                self._store(operands[0], self._pop())
            case "POPA":
                self.a = self._pop()
            case "X":
                first, second = self.value(operands[0]), self.value(operands[1])
                self._store(operands[0], second)
                self._store(operands[1], first)
            case "XA":
                held = self.value(operands[0])
                self._store(operands[0], self.a)
                self.a = held
            case "NOP":
                pass
            case _:  # pragma: no cover - the parser admits only the names above
                raise ScriptFailedError(f"no rule for {name}")

    def _command(self, instruction: Instruction) -> float | None:
        """A socket command run from the script: its result lands in A and F."""
        values = [self.value(operand) & 0xFFFFFFFF for operand in instruction.operands] + [0, 0]
        self.pc += 1
        delay_s: float | None = None
        if instruction.cmd == Cmd.MILS:
            result = Err.BAD_MILS_DELAY if values[0] > MAX_MILS else 0
            delay_s = values[0] / 1e3 if result == 0 else None
        elif instruction.cmd == Cmd.MICS:
            result = Err.BAD_MICS_DELAY if values[0] > MAX_MICS else 0
            delay_s = values[0] / 1e6 if result == 0 else None
        else:
            assert instruction.cmd is not None
            result = self.run_command(Command(instruction.cmd, values[0], values[1], 0), self.source)
        self.a = self.f = int32(result)
        return delay_s


_ARITHMETIC: dict[str, Callable[[int, int], int]] = {
    "ADD": lambda a, x: a + x,
    "SUB": lambda a, x: a - x,
    "MLT": lambda a, x: a * x,
    "AND": lambda a, x: a & x,
    "OR": lambda a, x: a | x,
    "XOR": lambda a, x: a ^ x,
    "RLA": lambda a, x: a << (x & 31),
    "RRA": lambda a, x: a >> (x & 31),
    "INRA": lambda a, _x: a + 1,
    "DCRA": lambda a, _x: a - 1,
}
_CONDITIONS: dict[str, Callable[[int], bool]] = {
    "JMP": lambda _f: True,
    "JZ": lambda f: f == 0,
    "JNZ": lambda f: f != 0,
    "JM": lambda f: f < 0,
    "JP": lambda f: f >= 0,
}
_REGISTER_OPS: dict[str, Callable[[int, int], int]] = {
    "INR": lambda r, _x: r + 1,
    "DCR": lambda r, _x: r - 1,
    "RL": lambda r, x: r << (x & 31),
    "RR": lambda r, x: r >> (x & 31),
}
