"""The virtual pigpiod's notification handles (NOIB, NB, NP, NC) and the reports queued for them.

Not thread-safe: the server holds its lock around every call. Reports are queued by `report` from whichever thread
drives the pins and written by `flush` on the server's loop, so each handle's reports keep their sequence order.
A handle's reports are numbered from 0 (16 bits, wrapping); reports lost on purpose (`lose`) or dropped because a
reader leaves more than `send_buffer_limit` bytes unread skip their sequence numbers, as pigpiod's do.
"""

from __future__ import annotations

import asyncio
from collections import deque
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from drivers.pigpiod.protocol import REPORT_SIZE, Cmd, Command, Err, encode_reports

MAX_HANDLES = 32
U32 = npt.NDArray[np.uint32]


@dataclass(slots=True)
class _Notifier:
    """One notification handle opened with NOIB on a socket."""

    transport: asyncio.Transport
    mask: int = 0
    paused: bool = True
    seq: int = 0
    to_lose: int = 0
    pending: deque[bytes] = field(default_factory=deque)


class NotifyHandles:
    """Every open notification handle, its mask and its queued reports."""

    def __init__(self, send_buffer_limit: int) -> None:
        self.send_buffer_limit = send_buffer_limit
        self._notifiers: dict[int, _Notifier] = {}
        self._last_report_tick: int | None = None
        self._flush_scheduled = False
        self.reports_sent = 0
        self.reports_lost = 0

    def open(self, transport: asyncio.Transport) -> int:
        """NOIB: a new handle whose reports go to `transport`, or PI_NO_HANDLE."""
        free = next((h for h in range(MAX_HANDLES) if h not in self._notifiers), None)
        if free is None:
            return Err.NO_HANDLE
        self._notifiers[free] = _Notifier(transport)
        return free

    def command(self, command: Command) -> int:
        """NB (begin with a mask), NP (pause) or NC (close) on a handle."""
        notifier = self._notifiers.get(command.p1)
        if notifier is None:
            return Err.BAD_HANDLE
        if command.cmd == Cmd.NB:
            notifier.mask, notifier.paused = command.p2, False
        elif command.cmd == Cmd.NP:
            notifier.paused = True
        else:
            del self._notifiers[command.p1]
            notifier.transport.close()  # pigpiod closes a NOIB socket with its handle
        return 0

    def close(self, handle: int) -> None:
        """Forget a handle whose socket went away."""
        self._notifiers.pop(handle, None)

    def lose(self, count: int) -> None:
        """Drop the next `count` reports of every handle, skipping their sequence numbers."""
        for notifier in self._notifiers.values():
            notifier.to_lose += count

    def monitored(self) -> dict[int, int]:
        """Each handle and the bank-1 mask it monitors (0 while paused)."""
        return {handle: 0 if n.paused else n.mask for handle, n in self._notifiers.items()}

    def report(self, ticks: U32, words: U32, previous: int) -> bool:
        """Queue the reports of bank-1 changes for every handle monitoring a changed bit.

        Returns True when the caller must schedule `flush` on the server's loop (none is scheduled yet).
        """
        if not len(ticks):
            return False
        if self._last_report_tick is not None:
            # Glitch-delayed stamps may fall before the last report sent: hold them at it, keeping ticks ordered.
            since = (ticks - np.uint32(self._last_report_tick)).view(np.int32)
            ticks = (np.maximum.accumulate(np.maximum(since, 0)).astype(np.uint32) + self._last_report_tick).astype(
                np.uint32
            )
        self._last_report_tick = int(ticks[-1])
        changed = words ^ np.concatenate((np.array([previous], dtype=np.uint32), words[:-1]))
        for notifier in self._notifiers.values():
            if notifier.paused or not notifier.mask:
                continue
            selected = np.flatnonzero(changed & np.uint32(notifier.mask))
            count = len(selected)
            if not count:
                continue
            seq = ((notifier.seq + np.arange(count)) & 0xFFFF).astype(np.uint16)
            notifier.seq += count
            lose = min(notifier.to_lose, count)
            notifier.to_lose -= lose
            self.reports_lost += lose
            if lose < count:
                kept = selected[lose:]
                notifier.pending.append(encode_reports(seq[lose:], ticks[kept], words[kept]))
        if self._flush_scheduled or not any(n.pending for n in self._notifiers.values()):
            return False
        self._flush_scheduled = True
        return True

    def flush(self) -> None:
        """Write queued reports to their sockets (on the server's loop)."""
        self._flush_scheduled = False
        for notifier in self._notifiers.values():
            if not notifier.pending:
                continue
            data = b"".join(notifier.pending)
            notifier.pending.clear()
            if notifier.transport.is_closing():
                continue
            count = len(data) // REPORT_SIZE
            if notifier.transport.get_write_buffer_size() > self.send_buffer_limit:
                self.reports_lost += count  # pigpiod drops what a slow reader cannot take
                continue
            notifier.transport.write(data)
            self.reports_sent += count
