"""A virtual GPIO chip whose line requests deliver real `struct gpio_v2_line_event` records through a pipe.

Theory of operation: the chip holds the levels of its lines. `open()` has the signature of
drivers.gpiod.lines.open_event_lines and returns a request whose `fd` is the read end of a fresh pipe, as the kernel
returns an anonymous file for a request. The simulator drives lines in bulk with `drive_levels(timestamps_ns,
levels, mask)`, the shape of the virtual pigpiod's method, from the edge generator the virtual robot uses
(robotd.sim.edges, drivers.virtual.quadrature_signal): every changed requested line becomes one 48-byte record with its
type (rising or falling), offset, request-wide seqno from 1 and per-line seqno from 1, written to the pipe in one
numpy-built `bytes`. `lose_events(n)` drops the next n events while their sequence numbers still advance, which is
what the kernel's overflow leaves behind; `unplug()` closes the write end, so the reader sees end of file.

Not modelled: bias, drive and debounce (the lines read `initial_levels` until driven; the settings are recorded in
`requests` only); the kernel buffer's size (the pipe's capacity, 64 KiB or 1365 events, stands for it) and its
overflow order: the kernel drops the oldest event, here events that do not fit are dropped newest first, in chunks of
up to 85 records, still leaving a seqno gap; an edge's type read late by the kernel's IRQ thread (here it is always
the level driven); other clocks than CLOCK_MONOTONIC; line info, reconfiguration and output lines.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from drivers.gpiod.events import EVENT_SIZE, FALLING_EDGE, RISING_EDGE, encode_events
from drivers.gpiod.lines import EventLineSettings

ATOMIC_WRITE = 4096 // EVENT_SIZE * EVENT_SIZE
"""The largest write the pipe takes whole or not at all (PIPE_BUF): 85 records."""


def level_change_events(
    timestamps_ns: npt.NDArray[np.int64], words: npt.NDArray[np.uint32], previous: int, lines: Sequence[int]
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.uint32], npt.NDArray[np.uint32]]:
    """(timestamps, ids, offsets) of one event per change of a line of `lines` along the level words.

    Events keep the words' order; lines that change in the same word come out in offset order, at the same time.
    """
    changed = words ^ np.concatenate((np.array([previous], dtype=np.uint32), words[:-1]))
    where: list[npt.NDArray[np.int64]] = []
    offsets: list[npt.NDArray[np.uint32]] = []
    for line in sorted(lines):
        at = np.flatnonzero((changed >> np.uint32(line)) & np.uint32(1))
        where.append(at)
        offsets.append(np.full(len(at), line, dtype=np.uint32))
    index = np.concatenate(where) if where else np.zeros(0, dtype=np.int64)
    offset = np.concatenate(offsets) if offsets else np.zeros(0, dtype=np.uint32)
    order = np.argsort(index, kind="stable")
    index, offset = index[order], offset[order]
    rising = (words[index] >> offset) & np.uint32(1)
    ids = np.where(rising == 1, RISING_EDGE, FALLING_EDGE).astype(np.uint32)
    return timestamps_ns[index], ids, offset


@dataclass(slots=True)
class _PipeRequest:
    """One request: the pipe's two ends and its sequence counters."""

    chip: VirtualEventLines
    offsets: list[int]
    fd: int
    write_fd: int
    seqno: int = 0
    line_seqno: dict[int, int] = field(default_factory=dict)
    released: bool = False

    def levels(self) -> int:
        """The requested lines' present levels."""
        mask = sum(1 << line for line in self.offsets)
        return self.chip.levels & mask

    def release(self) -> None:
        """Close the read end (and the write end, if the chip still holds it)."""
        self.chip._forget(self)
        if not self.released:
            self.released = True
            os.close(self.fd)


class VirtualEventLines:
    """A GPIO chip for tests and benchmarks; see the module docstring for what it models and what not."""

    def __init__(self, initial_levels: int = 0) -> None:
        self.levels = initial_levels & 0xFFFFFFFF
        """The lines' levels, bit n = line n."""
        self.requests: list[tuple[list[int], EventLineSettings]] = []
        """Every request opened, with the settings it asked for."""
        self.events_written = 0
        self.events_dropped = 0
        self._to_lose = 0
        self._lock = threading.Lock()
        self._open: _PipeRequest | None = None

    def open(self, offsets: Sequence[int], settings: EventLineSettings) -> _PipeRequest:
        """Request `offsets` with edge detection (the signature of drivers.gpiod.lines.open_event_lines)."""
        with self._lock:
            if self._open is not None:
                raise OSError(16, "Device or resource busy: the lines are already requested")
            read_fd, write_fd = os.pipe()
            os.set_blocking(write_fd, False)  # a full pipe drops events, as a full kernel buffer does
            request = _PipeRequest(self, list(offsets), read_fd, write_fd, line_seqno=dict.fromkeys(offsets, 0))
            self.requests.append((list(offsets), settings))
            self._open = request
            return request

    @property
    def requested(self) -> list[int]:
        """The lines of the open request ([] while none is open)."""
        request = self._open
        return list(request.offsets) if request is not None else []

    def _forget(self, request: _PipeRequest) -> None:
        with self._lock:
            if self._open is request:
                self._open = None
                os.close(request.write_fd)

    def drive_levels(self, timestamps_ns: npt.ArrayLike, levels: npt.ArrayLike, mask: int) -> None:
        """Drive the lines of `mask`: after `timestamps_ns[i]` (CLOCK_MONOTONIC) they read `levels[i]`."""
        stamps = np.ascontiguousarray(timestamps_ns, dtype=np.int64)
        words_in = np.ascontiguousarray(levels, dtype=np.uint32)
        if stamps.ndim != 1 or stamps.shape != words_in.shape:
            raise ValueError("timestamps and levels must be 1-D arrays of the same length")
        if not len(stamps):
            return
        with self._lock:
            previous = self.levels
            words = (words_in & np.uint32(mask)) | np.uint32(previous & ~mask & 0xFFFFFFFF)
            self.levels = int(words[-1])
            request = self._open
            if request is None:
                return
            stamps_out, ids, offsets = level_change_events(stamps, words, previous, request.offsets)
            self._emit(request, stamps_out, ids, offsets)

    def drive_edges(self, line: int, timestamps_ns: npt.ArrayLike, levels: npt.ArrayLike) -> None:
        """Drive one line: it takes `levels[i]` (0 or 1) at `timestamps_ns[i]`."""
        bits = np.asarray(levels, dtype=np.uint32) << np.uint32(line)
        self.drive_levels(timestamps_ns, bits, 1 << line)

    def _emit(
        self,
        request: _PipeRequest,
        stamps: npt.NDArray[np.int64],
        ids: npt.NDArray[np.uint32],
        offsets: npt.NDArray[np.uint32],
    ) -> None:
        count = len(ids)
        if not count:
            return
        seqnos = (request.seqno + 1 + np.arange(count)) & 0xFFFFFFFF
        request.seqno += count
        line_seqnos = np.zeros(count, dtype=np.int64)
        for line in request.offsets:
            on_line = offsets == line
            line_seqnos[on_line] = request.line_seqno[line] + 1 + np.arange(int(on_line.sum()))
            request.line_seqno[line] += int(on_line.sum())
        lose = min(self._to_lose, count)
        self._to_lose -= lose
        self.events_dropped += lose
        data = encode_events(stamps[lose:], ids[lose:], offsets[lose:], seqnos[lose:], line_seqnos[lose:])
        for start in range(0, len(data), ATOMIC_WRITE):
            try:
                os.write(request.write_fd, data[start : start + ATOMIC_WRITE])
            except BlockingIOError:
                self.events_dropped += (len(data) - start) // EVENT_SIZE  # the reader is behind: the rest is lost
                break
            self.events_written += len(data[start : start + ATOMIC_WRITE]) // EVENT_SIZE

    def lose_events(self, count: int) -> None:
        """Drop the next `count` events, their sequence numbers skipped as the kernel's overflow skips them."""
        with self._lock:
            self._to_lose += count

    def unplug(self) -> None:
        """Close the open request's write end: its reader sees end of file (the request has failed)."""
        with self._lock:
            request, self._open = self._open, None
            if request is not None:
                os.close(request.write_fd)
