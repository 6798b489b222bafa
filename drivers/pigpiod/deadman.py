"""A deadman inside pigpiod: a pigpio script that stops the motors unless its owner keeps bumping a heartbeat.

Theory of operation. pigpiod keeps generating PWM after its client is gone, so an owner that is killed, stopped or
hung would leave the wheels driving. The deadman lives where the owner's death cannot reach it: a script stored and
run inside pigpiod (PROC, PROCR). The owner bumps the script's parameter p0 (PROCU) a few times per timeout; the
script reads p0 every `slice_ms`, noting pigpiod's tick (microseconds) at each read. Armed by the first bump, it
writes every enable pin low, then every direction pin low (W also stops PWM; enables first, so the L298 never sees
a direction input change under a live enable) at the first read that finds p0 unchanged for `timeout` since the read
before its last change; then it counts the trip in p1 and waits, disarmed, for p0 to change again: an owner resumed
after SIGSTOP arms it with its next bump. Timing from the tick, not by counting reads, keeps the reads' own delays
from adding up: the pins go low between `timeout - slice` and `timeout + slice` after the last bump, plus one of
pigpiod's scheduling delays.

Parameters: p0 the heartbeat (the owner's), p1 the trips (the script's), p8 the mask of the motor pins and p9
`SIGNATURE`. p8 and p9 mark a script as a robotd deadman guarding those pins: whoever takes the pins next removes a
deadman left by a killed owner (`remove_deadmen`), which would otherwise stop the new owner's motors.
Variables: v0 the last heartbeat seen, v2 the tick of the read before it changed (the bump came later), v3 the tick
of the latest read, v4 the tick of the read before.

The bump never waits: `bump()` writes PROCU (and, every `status_every` bumps, PROCP) to the socket and returns;
`watch()` reads the answers in order, reports new trips, and raises DeadmanLostError when pigpiod refuses a command,
the script is no longer running or the socket closes. The answers are held in the kernel between two status requests
and read together after each (PigpioLink.hold_answers): one wake-up per status, not one per heartbeat.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable, Sequence
from typing import Any, Protocol

from drivers.pigpiod.client import PigpioLink
from drivers.pigpiod.protocol import MAX_SCRIPTS, SCRIPT_STATUS, Cmd, Err, ScriptState, encode_params

SIGNATURE = 0x726F6264
"""p9 of every robotd deadman ("robd")."""
HEARTBEAT, TRIPS, PIN_MASK, SIGNATURE_PARAM = 0, 1, 8, 9
STATUS_S = 0.5
"""About how often a status request goes with a heartbeat: the answers are read then, and a trip is seen."""
MAX_OUTSTANDING = 64
"""Answers allowed to be owed before bumps stop: a pigpiod that stops answering stops hearing the heartbeat."""
MAX_MILS = 60_000
MAX_TIMEOUT_MS = 1_000_000
"""Far below the 35 minutes after which the difference of two 32-bit microsecond ticks turns negative."""


class DeadmanLostError(ConnectionError):
    """The deadman script no longer guards the motors (refused, halted, deleted, or pigpiod gone)."""


class Deadman(Protocol):
    """What the daemon needs from a deadman."""

    def bump(self) -> None:
        """Tell the deadman the owner is alive (never blocks)."""
        ...

    async def watch(self, on_trip: Callable[[int], None]) -> None:
        """Follow the deadman; call `on_trip(trips)` after it stopped the motors; raise when it is lost."""
        ...

    async def uninstall(self) -> None:
        """Stop and delete the deadman (a clean exit)."""
        ...

    def close(self) -> None:
        """Forget the deadman without touching pigpiod (its connection is gone)."""
        ...


def pin_mask(pins: Sequence[int]) -> int:
    """The bank-1 mask of some GPIOs (0-31)."""
    if any(not 0 <= pin < 32 for pin in pins):
        raise ValueError(f"the deadman guards GPIO 0-31 only, got {list(pins)}")
    return sum(1 << pin for pin in set(pins))


def deadman_script(enable_pins: Sequence[int], direction_pins: Sequence[int], slice_ms: int, timeout_ms: int) -> str:
    """The script's text: disarmed until p0 changes, then trips once p0 has not changed for `timeout_ms`."""
    if not 1 <= slice_ms <= MAX_MILS or not slice_ms <= timeout_ms <= MAX_TIMEOUT_MS:
        raise ValueError(f"need 1 <= slice_ms <= {MAX_MILS} and slice_ms <= timeout_ms <= {MAX_TIMEOUT_MS}")
    pin_mask([*enable_pins, *direction_pins])
    stop = " ".join(f"w {pin} 0" for pin in [*enable_pins, *direction_pins])  # enables first: the bridge rule
    read = f"lda v3 sta v4 mils {slice_ms} t sta v3 lda p0 cmp v0"  # the previous read's tick; sleep; tick; p0 - v0
    lines = (
        "ld v0 p0 t sta v3",  # the heartbeat as run: nothing to guard until it changes
        f"tag 0 {read} jz 0",  # disarmed: wait for a new heartbeat
        "tag 1 sta v0 lda v4 sta v2",  # a new heartbeat (A holds it), bumped after the read before this one
        f"tag 2 {read} jnz 1",  # armed: a newer heartbeat starts the wait again
        f"lda v3 sub v2 cmp {timeout_ms * 1000} jm 2",  # microseconds since then (32-bit ticks wrap: so does sub)
        f"{stop} inr p1 jmp 0",  # tripped: motors off, count it, disarm
    )
    return "\n".join(lines)  # pigpio scripts have no comments: they live here


class PigpioDeadman:
    """A deadman script running in pigpiod, bumped and watched over its own command socket."""

    def __init__(self, link: PigpioLink, script_id: int, *, status_every: int, connect_timeout_s: float) -> None:
        self._link = link
        self.script_id = script_id
        self._status_every = max(1, status_every)
        self._connect_timeout_s = connect_timeout_s
        self._heartbeat = 0
        self._bumps = 0
        self._outstanding = 0
        self._statuses_owed = 0
        self._closed = False
        self.trips = 0

    @classmethod
    async def install(
        cls,
        host: str,
        port: int,
        connect_timeout_s: float,
        enable_pins: Sequence[int],
        direction_pins: Sequence[int],
        *,
        timeout_s: float,
        period_s: float,
        heartbeat_s: float | None = None,
    ) -> PigpioDeadman:
        """Store and run a deadman for these pins, bumped about every `heartbeat_s` (default `period_s`); it trips
        `timeout_s` after the last bump.

        The script reads its heartbeat every period (whole milliseconds, at least 1), so the motors stop within
        `timeout_s` plus one period of the last bump. Raises PigpiodUnavailableError or PigpioCommandError.
        """
        slice_ms = max(1, int(period_s * 1000.0))
        timeout_ms = max(slice_ms, round(timeout_s * 1000.0))
        script = deadman_script(enable_pins, direction_pins, slice_ms, timeout_ms)
        params = [0] * 10
        params[PIN_MASK], params[SIGNATURE_PARAM] = pin_mask([*enable_pins, *direction_pins]), SIGNATURE
        link = await PigpioLink.connect(host, port, connect_timeout_s)
        try:
            script_id = await link.command(Cmd.PROC, extension=script.encode("ascii"))
            try:
                await _run_when_ready(link, script_id, params)
            except BaseException:
                with contextlib.suppress(Exception):
                    await link.command(Cmd.PROCD, script_id)
                raise
        except BaseException:
            await link.close()
            raise
        # the answers are read with a status request about every STATUS_S: a trip is noticed within that of the
        # owner's return (meanwhile the pins the script wrote low keep the wheels stopped), and a robot at rest
        # wakes for the answers only twice a second
        status_every = max(1, round(STATUS_S / (period_s if heartbeat_s is None else heartbeat_s)))
        return cls(link, script_id, status_every=status_every, connect_timeout_s=connect_timeout_s)

    def bump(self) -> None:
        """Write a new heartbeat (and now and then a status request) without waiting for pigpiod."""
        if self._closed or self._outstanding >= MAX_OUTSTANDING or self._link.is_closing():
            return
        self._heartbeat = (self._heartbeat + 1) & 0xFFFFFFFF
        self._link.post(Cmd.PROCU, self.script_id, 0, encode_params([self._heartbeat]))
        self._outstanding += 1
        self._bumps += 1
        if self._bumps % self._status_every == 0:
            self._link.post(Cmd.PROCP, self.script_id)
            self._outstanding += 1
            self._statuses_owed += 1
            self._link.release_answers()  # the heartbeats' answers held so far, then this one

    async def watch(self, on_trip: Callable[[int], None]) -> None:
        """Read pigpiod's answers to the bumps; call `on_trip` when the trip count grows; raise when lost."""
        self._link.hold_answers()
        while True:
            answer = await self._link.read_answer()
            self._outstanding -= 1
            if answer.result < 0:
                reason = Err(answer.result).name if answer.result in Err._value2member_map_ else answer.result
                raise DeadmanLostError(f"pigpiod refused the deadman's {Cmd(answer.cmd).name}: {reason}")
            if answer.cmd != Cmd.PROCP:
                continue
            self._statuses_owed -= 1
            if not self._statuses_owed:
                self._link.hold_answers()  # until the next status request
            state, *params = SCRIPT_STATUS.unpack(answer.data)
            if state not in (ScriptState.RUNNING, ScriptState.WAITING):
                raise DeadmanLostError(f"the deadman script is {ScriptState(state).name.lower()}")
            if params[TRIPS] != self.trips:
                self.trips = params[TRIPS]
                on_trip(self.trips)

    async def uninstall(self) -> None:
        """Stop and delete the script (PROCD halts it first), over a fresh socket; then forget it."""
        self.close()
        link = await PigpioLink.connect(self._link.host, self._link.port, self._connect_timeout_s)
        try:
            await link.command(Cmd.PROCD, self.script_id)
        finally:
            await link.close()

    def close(self) -> None:
        """Stop bumping and close the socket; the script, if pigpiod still runs it, trips and waits."""
        self._closed = True
        self._link.abort()


async def _run_when_ready(link: PigpioLink, script_id: int, params: list[int]) -> None:
    """PROCR once pigpiod has started the script's thread (until then PROCR answers PI_SCRIPT_NOT_READY)."""
    for _ in range(200):
        status = SCRIPT_STATUS.unpack(await link.query(Cmd.PROCP, script_id))[0]
        if status != ScriptState.INITING:
            await link.command(Cmd.PROCR, script_id, extension=encode_params(params))
            return
        await asyncio.sleep(0.005)
    raise TimeoutError(f"pigpiod did not start the deadman script {script_id}")


def find_deadmen(pi: Any, pins: Sequence[int]) -> list[int]:
    """Ids of the robotd deadman scripts guarding exactly these pins, asked with a `pigpio.pi` (blocking)."""
    signature = [0] * 10
    signature[PIN_MASK], signature[SIGNATURE_PARAM] = pin_mask(pins), SIGNATURE
    found = []
    for script_id in range(MAX_SCRIPTS):
        status, params = pi.script_status(script_id)  # an unused id answers PI_BAD_SCRIPT_ID and no parameters
        if status >= 0 and list(params[PIN_MASK:]) == signature[PIN_MASK:]:
            found.append(script_id)
    return found


def remove_deadmen(pi: Any, pins: Sequence[int]) -> int:
    """Stop and delete the robotd deadman scripts guarding these pins (a killed owner's); how many (blocking)."""
    import pigpio  # noqa: PLC0415 - callers already hold a pigpio connection

    removed = 0
    for script_id in find_deadmen(pi, pins):
        try:
            pi.delete_script(script_id)  # PROCD halts the script first
        except pigpio.error:
            continue  # gone meanwhile
        removed += 1
    return removed
