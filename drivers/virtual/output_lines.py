"""Output lines of a virtual GPIO chip, for the motors' direction inputs: every write recorded, in order.

`open` has the signature of drivers.gpiod.lines.open_output_lines and returns a request of `OutputLines`: its lines
start low, `set_values` changes several at once (one entry in `journal`, {"gpioN": "0" | "1", ...}, as one kernel
call changes them together), `release` gives them back. Lines held by a request are refused to another with EBUSY,
as the kernel refuses them.

Not modelled: what a released line does (it keeps its last level here); drive, bias, active-low; the chip's path
(any is accepted); reading lines back through the request.
"""

from __future__ import annotations

import errno
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

Journal = list[dict[str, str]]


@dataclass(slots=True)
class _OutputRequest:
    chip: VirtualOutputLines
    offsets: tuple[int, ...]
    released: bool = False

    def set_values(self, values: Mapping[int, int]) -> None:
        """Drive the lines of `values`, all at once."""
        if self.released:
            raise OSError(errno.EBADF, "the request was released")
        unknown = set(values) - set(self.offsets)
        if unknown:
            raise ValueError(f"lines {sorted(unknown)} are not in this request {list(self.offsets)}")
        if self.chip.fail_writes:
            self.chip.fail_writes -= 1
            raise OSError(errno.EIO, os.strerror(errno.EIO))
        for line, level in values.items():
            self.chip.levels[line] = 1 if level else 0
        self.chip.journal.append({f"gpio{line}": str(1 if level else 0) for line, level in values.items()})

    def release(self) -> None:
        """Give the lines back."""
        if not self.released:
            self.released = True
            self.chip.held -= set(self.offsets)


class VirtualOutputLines:
    """A GPIO chip's output lines for tests (see the module docstring)."""

    def __init__(self, journal: Journal | None = None) -> None:
        self.journal: Journal = journal if journal is not None else []
        self.levels: dict[int, int] = {}
        self.held: set[int] = set()
        self.requests: list[tuple[int, ...]] = []
        self.fail_writes = 0
        """The next this-many writes fail with EIO (a chip gone away)."""

    def open(self, offsets: Sequence[int], chip: str | None = None) -> _OutputRequest:  # noqa: ARG002 - any chip
        """Request `offsets` as outputs driven low (the signature of drivers.gpiod.lines.open_output_lines)."""
        busy = self.held & set(offsets)
        if busy:
            raise OSError(errno.EBUSY, f"lines {sorted(busy)} are held by another request")
        request = _OutputRequest(self, tuple(offsets))
        self.held |= set(offsets)
        self.requests.append(request.offsets)
        for line in offsets:
            self.levels[line] = 0
        self.journal.append({f"gpio{line}": "0" for line in offsets})
        return request

    def level(self, line: int) -> int:
        """A line's present level (0 for a line never requested)."""
        return self.levels.get(line, 0)
