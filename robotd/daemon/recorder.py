"""`robotd run --record`: the sensor log written by a thread, so that no sink can block the event loop.

Theory of operation. `Recorder.write()` runs on the loop and never waits: it puts the event on a bounded queue, or
counts it as dropped when the queue is full (a sink slower than the events: a stalled disk, an NFS mount gone away).
One writer thread takes the events, encodes them and writes the lines (the meta line first): what came since it last
woke, at once, then a flush, waking at most every drivers.pacing.BATCH_PERIOD_S, so the file is never more than a
moment behind. A write that fails (ENOSPC, EIO, ...) ends the recording with one ERROR line: the thread closes the file
and leaves, later events are counted as dropped, and the robot keeps running; an unexpected exception does the same
with its traceback.

An existing log is never overwritten nor appended to: `create_log` creates the file exclusively, and when the name is
taken it takes the first free `NAME.1.jsonl`, `NAME.2.jsonl`, ... systemd restarts a failed robotd with the same
command line, and the log of the run before the restart is the one that shows why it failed; refusing to start would
turn one failure into a robot that does not run at all, and appending would mix two runs (two metas, two clocks) in
one file.
"""

from __future__ import annotations

import contextlib
import enum
import logging
import queue
import threading
import time
from pathlib import Path
from typing import Any, TextIO

from drivers.pacing import sleep_out, take_waiting
from robotd.config.model import RobotdConfig
from robotd.logs.events import Event, Meta, encode

log = logging.getLogger("robotd.daemon.recorder")

QUEUE_EVENTS = 4096
"""Events held for the writer thread: about 50 s of the daemon's events (wheels at 50 Hz, fixes, commands)."""
MAX_NUMBERED = 999
"""`create_log` gives up after NAME.999.jsonl: a folder of a thousand restarts needs a person, not another file."""
CLOSE_TIMEOUT_S = 2.0
"""How long `close` waits for the writer to drain the queue; a stuck sink is left behind, not waited for."""


_IDLE_CHECK_S = 0.5  # how often an idle writer checks whether it was closed without being told (a full queue)


class RecordingError(Exception):
    """The sensor log could not be created (one line, for the operator)."""


class RecorderState(enum.Enum):
    """Where the recording stands."""

    RECORDING = "recording"
    FAILED = "failed"  # a write failed: recording stopped, the robot runs on
    CLOSED = "closed"


def create_log(path: Path) -> tuple[TextIO, Path]:
    """A new, empty sensor log at `path`, or at the first free `NAME.N.SUFFIX` beside it; never an existing file."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise RecordingError(f"cannot create the folder of {path}: {error.strerror or error}") from None
    candidates = [path, *(path.with_name(f"{path.stem}.{n}{path.suffix}") for n in range(1, MAX_NUMBERED + 1))]
    for candidate in candidates:
        try:
            stream = candidate.open("x", encoding="utf-8")  # O_EXCL: another process cannot slip in between
        except FileExistsError:
            continue
        except OSError as error:
            raise RecordingError(f"cannot create {candidate}: {error.strerror or error}") from None
        return stream, candidate
    raise RecordingError(f"{path} and {path.stem}.1{path.suffix} to .{MAX_NUMBERED}{path.suffix} all exist")


def daemon_meta(config: RobotdConfig) -> Meta:
    """The meta line of a log `robotd run` records: the robot's geometry, as configured."""
    robot = config.robot
    return Meta(
        robot={
            "wheel_radius": robot.wheel_radius_m,
            "lx": robot.lx_m,
            "ly": robot.ly_m,
            "counts_per_rev": config.encoders.counts_per_rev,
            "ips_offset": list(robot.ips_offset_m),
        },
        source="robotd run --record",
    )


class Recorder:
    """Writes sensor log events from a thread through a bounded queue: the loop only enqueues (module docstring)."""

    def __init__(self, stream: TextIO, meta: Meta, *, capacity: int | None = None) -> None:
        self.name = str(getattr(stream, "name", "the sensor log"))
        self._stream = stream
        # None tells the writer thread to flush, close the file and leave; + 1 for the meta line
        self._queue: queue.Queue[Event | Meta | None] = queue.Queue(maxsize=(capacity or QUEUE_EVENTS) + 1)
        self._queue.put_nowait(meta)
        self._state = RecorderState.RECORDING
        self.written = 0  # events written by the thread (the meta line not counted)
        self.dropped = 0  # events the loop could not hand over: queue full, or recording stopped
        self._thread = threading.Thread(target=self._write_all, name="recorder", daemon=True)

    @property
    def state(self) -> RecorderState:
        """Recording, failed (a write failed) or closed."""
        return self._state

    def start(self) -> None:
        """Start the writer thread."""
        self._thread.start()

    def write(self, event: Event) -> None:
        """Enqueue one event for the writer thread; never blocks (a full queue or a stopped recording drops it,
        counted)."""
        if self._state is not RecorderState.RECORDING:
            self.dropped += 1
            return
        try:
            self._queue.put_nowait(event)
        except queue.Full:
            self.dropped += 1

    def counters(self) -> dict[str, Any]:
        """For the status message."""
        return {"state": self._state.value, "path": self.name, "written": self.written, "dropped": self.dropped}

    def close(self, timeout_s: float = CLOSE_TIMEOUT_S) -> None:
        """Write what is queued and close the file, waiting at most `timeout_s` for a slow sink."""
        if self._state is RecorderState.RECORDING:
            self._state = RecorderState.CLOSED
        if not self._thread.is_alive():
            if self._thread.ident is None:  # never started: nothing else touches the file
                self._close_stream()
            return
        with contextlib.suppress(queue.Full):  # a stuck sink: the join below gives up too, and says so
            self._queue.put(None, timeout=timeout_s)
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            log.warning(
                "recording: %s did not accept the last %d events within %.1f s; left unwritten",
                self.name, self._queue.qsize(), timeout_s,
            )  # fmt: skip

    # --- the writer thread ---------------------------------------------------------------------------------------

    def _write_all(self) -> None:
        try:
            while True:
                try:
                    first = self._queue.get(timeout=_IDLE_CHECK_S)
                except queue.Empty:
                    if self._state is RecorderState.RECORDING:
                        continue
                    first = None  # closed while the queue was too full to take the stop: drained now
                woke = time.monotonic()
                for item in take_waiting(first, self._queue):
                    if item is None:
                        self._stream.flush()
                        return
                    self._stream.write(encode(item) + "\n")
                    if not isinstance(item, Meta):
                        self.written += 1
                self._stream.flush()
                sleep_out(woke)
        except OSError as error:
            self._state = RecorderState.FAILED
            log.error(  # an operational failure: one line, no traceback
                "recording stopped: cannot write %s: %s; the robot keeps running", self.name, error.strerror or error
            )
        except Exception:
            self._state = RecorderState.FAILED
            log.exception("recording stopped by an unexpected error; the robot keeps running")
        finally:
            self._close_stream()

    def _close_stream(self) -> None:
        with contextlib.suppress(OSError):  # the buffered tail of a failed log cannot be written either: already said
            self._stream.close()
