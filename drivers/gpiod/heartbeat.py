"""The heartbeat deadman's state machine, sans I/O: bytes from the owner and the time in, "stop the motors now" out.

Theory of operation. The owner writes one byte per control period on a pipe: `HEARTBEAT` ("I am alive"), `DISARM`
(its deadman is removed on a clean exit; only death is guarded from then on) or `CLOSING` (a clean close follows:
the owner has stopped its motors itself). The watchdog process feeds what it reads to `HeartbeatMonitor.feed` with
the time of the read and asks `expired(now)` when its wait for more bytes times out.

    state      event                                   next       action
    DISARMED   HEARTBEAT                               ARMED      the deadline is now + timeout
    ARMED      HEARTBEAT                               ARMED      the deadline moves to now + timeout
    ARMED      no HEARTBEAT by the deadline            TRIPPED    stop the motors, count the trip
    TRIPPED    HEARTBEAT                               ARMED      re-armed: an owner resumed after SIGSTOP
    any        DISARM                                  DISARMED   -

A monitor without a timeout never arms: it guards death only (end of file on the pipe, seen by its caller). This is
the pigpio deadman script's behaviour (drivers.pigpiod.deadman): armed by the first bump, tripped once, re-armed by
the next bump.
"""

from __future__ import annotations

import enum

HEARTBEAT, DISARM, CLOSING = b"H", b"D", b"Q"


class Guard(enum.Enum):
    """What the deadman is doing."""

    DISARMED = "disarmed"
    ARMED = "armed"
    TRIPPED = "tripped"


class HeartbeatMonitor:
    """The state machine of the module docstring; `timeout_s` None: never armed."""

    def __init__(self, timeout_s: float | None) -> None:
        self.timeout_s = timeout_s
        self.state = Guard.DISARMED
        self.deadline = 0.0
        self.trips = 0
        self.closing = False
        """The owner said a clean close follows: its end of file is not a death."""

    def feed(self, data: bytes, now: float) -> None:
        """The bytes of one read at time `now`, in order."""
        for code in data:
            byte = bytes((code,))
            if byte == HEARTBEAT and self.timeout_s is not None:
                self.state, self.deadline = Guard.ARMED, now + self.timeout_s
            elif byte == DISARM:
                self.state = Guard.DISARMED
            elif byte == CLOSING:
                self.closing = True
            # anything else is ignored: the pipe is the owner's alone, and a newer owner may say more

    def wait_s(self, now: float) -> float | None:
        """How long the caller may wait for bytes before it must call `expired`; None: as long as it likes."""
        return max(0.0, self.deadline - now) if self.state is Guard.ARMED else None

    def expired(self, now: float) -> bool:
        """True once per trip: armed and the deadline passed (the caller then stops the motors)."""
        if self.state is not Guard.ARMED or now < self.deadline:
            return False
        self.state = Guard.TRIPPED
        self.trips += 1
        return True
