"""The daemon's viewer: Foxglove's WebSocket server and/or an MCAP recording, fed from the event loop through a
bounded queue and published by one thread.

Theory of operation. The daemon calls `LiveViewer`'s methods from its loop; each only puts a small tuple on a bounded
queue and returns (a full queue drops the item and counts it: a viewer must never cost a control period). One thread
takes the items in order and hands them to a `Publisher` (robotd.viz.publisher), which builds the Foxglove messages
and logs them on channels of a private SDK context. The context's sinks are the WebSocket server (each client has
its own bounded backlog in the SDK: a slow viewer loses its oldest messages) and, with `run --record FILE.mcap`, the
SDK's MCAP writer: both get the same channels, so the file replays (its `/log/*` records) and views (the rest).
Log lines reach the viewer through a logging handler that enqueues them the same way.
"""

from __future__ import annotations

import contextlib
import enum
import logging
import queue
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Protocol

import foxglove
from foxglove import Context
from foxglove.websocket import ServerListener, WebSocketServer

from drivers.marvelmind.events import StationaryBeacons
from drivers.pacing import sleep_out, take_waiting
from robotd.config.model import RobotdConfig
from robotd.config.viewer import ViewerConfig
from robotd.estimation.fixgate import Diagnostics
from robotd.kinematics import Geometry
from robotd.logs import events
from robotd.viz.logtopics import LogClock
from robotd.viz.publisher import Publisher, RobotModel

log = logging.getLogger("robotd.viz")

CLOSE_TIMEOUT_S = 2.0
_STOP = ("stop",)


class _Listener(ServerListener):
    """Counts the viewers' subscriptions (the SDK calls it from its own threads)."""

    def __init__(self) -> None:
        self.subscriptions = 0
        self.clients: set[int] = set()

    def on_subscribe(self, client: Any, channel: Any) -> None:  # noqa: ARG002 - the SDK's listener protocol
        self.subscriptions += 1
        self.clients.add(int(client.id))

    def on_unsubscribe(self, client: Any, channel: Any) -> None:  # noqa: ARG002 - same
        self.subscriptions = max(0, self.subscriptions - 1)


class LiveViewer:
    """The daemon's viewer: enqueue from the loop, publish from a thread (see the module docstring)."""

    def __init__(
        self,
        robot: RobotModel,
        config: ViewerConfig,
        *,
        serve: bool,
        record_path: Path | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.config = config
        self.serve = serve
        self.record_path = record_path
        # the log's clock is the daemon's monotonic one; Foxglove's timeline wants Unix time
        offset_ns = time.time_ns() - round(clock() * 1e9)
        self._context = Context()
        self._publisher = Publisher(
            self._context, robot, LogClock(offset_ns), trail_s=config.trail_s, trail_period_s=1.0 / config.trail_rate_hz
        )
        self._queue: queue.Queue[tuple[Any, ...]] = queue.Queue(maxsize=config.queue)
        self._listener = _Listener()
        self._server: WebSocketServer | None = None
        self._writer: foxglove.MCAPWriter | None = None
        self._thread = threading.Thread(target=self._publish_all, name="viewer", daemon=True)
        self.published = 0
        self.dropped = 0
        self.failed = False
        self.port: int | None = None
        self._clock = clock
        self._handler: LogHandler | None = None
        self._last_control: float | None = None  # the previous control period's time (its period in /control)

    # --- life -------------------------------------------------------------------------------------------------

    def start(self) -> None:
        """Open the MCAP file and start the server (as configured), then the publishing thread; a server that cannot
        start (the port taken) is one ERROR line, and the robot runs on without it."""
        if self.record_path is not None:
            self._writer = foxglove.open_mcap(self.record_path, allow_overwrite=True, context=self._context)
        if self.serve:
            try:
                self._server = foxglove.start_server(
                    name="robotd",
                    host=self.config.host,
                    port=self.config.port,
                    context=self._context,
                    server_listener=self._listener,
                    message_backlog_size=self.config.client_backlog,
                )
            except Exception as error:  # noqa: BLE001 - the SDK raises RuntimeError with the OS's reason
                self.failed = True
                log.error(
                    "live view: cannot serve on %s:%d: %s; the robot runs without it", self.config.host,
                    self.config.port, error,
                )  # fmt: skip
            else:
                self.port = self._server.port
                log.info("live view: ws://%s:%d (Foxglove: Open connection)", self.config.host, self.port)
        self._handler = LogHandler(self, self._clock)
        logging.getLogger("robotd").addHandler(self._handler)
        self._thread.start()

    def close(self, timeout_s: float = CLOSE_TIMEOUT_S) -> None:
        """Publish what is queued (waiting at most `timeout_s`), finish the MCAP file, stop the server."""
        if self._handler is not None:
            logging.getLogger("robotd").removeHandler(self._handler)
            self._handler = None
        if self._thread.is_alive():
            with contextlib.suppress(queue.Full):
                self._queue.put(_STOP, timeout=timeout_s)
            self._thread.join(timeout_s)
        if self._writer is not None:
            self._writer.close()
            self._writer = None
        if self._server is not None:
            self._server.stop()
            self._server = None

    # --- from the loop: enqueue and return ----------------------------------------------------------------------

    def _put(self, item: tuple[Any, ...]) -> None:
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            self.dropped += 1

    def record(self, record: events.Record) -> None:
        """A sensor log record (for the `/log/*` channels and the odometry alone)."""
        self._put(("record", record))

    def fix(self, t: float, x: float, y: float, diagnostics: Diagnostics | None) -> None:
        """A fix and the estimator's record of it (None: dropped before any verdict)."""
        self._put(("fix", t, x, y, diagnostics))

    def beacons(self, event: StationaryBeacons) -> None:
        """The stationary beacons the hedgehog reported."""
        self._put(("beacons", event))

    def control(self, t: float, output: ControlSample, measured: Sequence[float]) -> None:
        """One period of the control loop: its output (set points, duties, state) and the measured wheel speeds."""
        self._put(("control", t, output, measured))

    def pose(self, message: dict[str, Any]) -> None:
        """A pose message of the pose socket (not modified)."""
        self._put(("pose", message))

    def status(self, message: dict[str, Any]) -> None:
        """A status message of the pose socket."""
        self._put(("status", message))

    def log_line(self, t: float, level: int, name: str, text: str) -> None:
        """One log line."""
        self._put(("log", t, level, name, text))

    def counters(self) -> dict[str, Any]:
        """For the status message."""
        return {
            "state": "failed" if self.failed else "running",
            "port": self.port,
            "recording": str(self.record_path) if self.record_path is not None else None,
            "subscriptions": self._listener.subscriptions,
            "published": self.published,
            "dropped": self.dropped,
            "queued": self._queue.qsize(),
        }

    # --- the thread -----------------------------------------------------------------------------------------------

    def _publish_all(self) -> None:
        """Publish the queued items in order until the stop item: all that came since the last wake-up at once, at
        most once a drivers.pacing.BATCH_PERIOD_S."""
        while True:
            first = self._queue.get()  # asleep until there is something to publish
            woke = time.monotonic()
            for item in take_waiting(first, self._queue):
                if item[0] == "stop":
                    return
                self._publish(item)
            sleep_out(woke)

    def _publish(self, item: tuple[Any, ...]) -> None:
        """One queued item published; a failure is logged once, with its traceback, and the thread goes on."""
        publisher = self._publisher
        kind = item[0]
        try:
            if kind == "record":
                publisher.record(item[1])
            elif kind == "pose":
                publisher.pose(item[1])
            elif kind == "control":
                _, t, output, measured = item
                last, self._last_control = self._last_control, t
                publisher.control(control_message(t, output, measured, None if last is None else 1000.0 * (t - last)))
            elif kind == "fix":
                _, t, x, y, diagnostics = item
                publisher.verdict(t, x, y, *verdict_of(diagnostics))
            elif kind == "beacons":
                event = item[1]
                stationary = [(b.address, b.x, b.y, b.z, b.applicable) for b in event.beacons]
                publisher.beacons(event.arrival, stationary)
            elif kind == "status":
                publisher.status(item[1])
            elif kind == "log":
                publisher.log_line(*item[1:])
            self.published += 1
        except Exception:  # a bug in the view must not take the daemon down: say it once, with its traceback
            if not self.failed:
                self.failed = True
                log.exception("live view: could not publish a %s item; the robot keeps running", kind)


class ControlSample(Protocol):
    """What the viewer reads of a control period's output (robotd.daemon.control.ControlOutput)."""

    @property
    def duties(self) -> Sequence[float]: ...
    @property
    def wheel_setpoints(self) -> Sequence[float]: ...
    @property
    def state(self) -> enum.Enum: ...


def control_message(
    t: float, output: ControlSample, measured: Sequence[float], period_ms: float | None
) -> dict[str, Any]:
    """The `/control` message: wheel speed set points and measurements (rad/s), duties, state, loop period."""
    return {
        "t": t,
        "setpoint_rad_s": list(output.wheel_setpoints),
        "measured_rad_s": list(measured),
        "duty": list(output.duties),
        "state": output.state.value,
        "period_ms": period_ms,
    }


def verdict_of(diagnostics: Diagnostics | None) -> tuple[str, dict[str, Any]]:
    """A fix's verdict and the figures worth plotting (NIS, gate, innovation, the IPS noise in use)."""
    if diagnostics is None:
        return "dropped", {}
    return diagnostics.verdict.value, {
        "t_meas": diagnostics.t_meas,
        "nis": diagnostics.nis,
        "gate": diagnostics.gate,
        "innovation_m": list(diagnostics.nu),
        "ips_sigma_m": diagnostics.r_m,
        "accepted": diagnostics.accepted,
    }


class LogHandler(logging.Handler):
    """Hands log records to the viewer (from any thread; never blocks)."""

    def __init__(self, viewer: LiveViewer, clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__(logging.INFO)
        self.viewer = viewer
        self.clock = clock

    def emit(self, record: logging.LogRecord) -> None:
        """Enqueue the formatted line."""
        if record.name == log.name:  # the viewer's own lines: a failing view must not feed itself
            return
        try:
            text = record.getMessage()
        except Exception:  # noqa: BLE001 - a bad format string: logging's own policy is to report, not raise
            self.handleError(record)
            return
        self.viewer.log_line(self.clock(), record.levelno, record.name, text)


class EventSink(Protocol):
    """Where the daemon writes its sensor log events (robotd.daemon.recorder.Recorder, or `Tee`)."""

    def start(self) -> None: ...
    def write(self, event: events.Event) -> None: ...
    def close(self) -> None: ...
    def counters(self) -> dict[str, Any]: ...


class Tee:
    """The daemon's sensor log events to its JSON Lines recorder (when recording one) and to the viewer."""

    def __init__(self, recorder: EventSink | None, viewer: LiveViewer, meta: events.Meta) -> None:
        self.recorder = recorder
        self.viewer = viewer
        self.meta = meta

    def start(self) -> None:
        """Start both; the viewer's records open with the log's meta, as the JSON Lines log does."""
        if self.recorder is not None:
            self.recorder.start()
        self.viewer.record(self.meta)
        self.viewer.start()

    def write(self, event: events.Event) -> None:
        """Hand the event to both; neither blocks."""
        if self.recorder is not None:
            self.recorder.write(event)
        self.viewer.record(event)

    def close(self) -> None:
        """Close both (the recorder first: its file is the one a replay reads)."""
        if self.recorder is not None:
            self.recorder.close()
        self.viewer.close()

    def counters(self) -> dict[str, Any]:
        """The JSON Lines recorder's counters, or the MCAP recording's."""
        if self.recorder is not None:
            return self.recorder.counters()
        viewer = self.viewer
        recording = viewer.record_path is not None
        return {
            "state": ("failed" if viewer.failed else "recording") if recording else "off",
            "path": str(viewer.record_path) if recording else None,
            "written": viewer.published,
            "dropped": viewer.dropped,
        }


def viewer_for(
    config: RobotdConfig, geometry: Geometry, record_mcap: Path | None, clock: Callable[[], float]
) -> LiveViewer | None:
    """The daemon's viewer: serving when `viewer.enabled`, recording when given an MCAP path; None when neither."""
    if not config.viewer.enabled and record_mcap is None:
        return None
    robot = RobotModel(config.ekf, geometry, config.robot.ips_offset_m, config.encoders.counts_per_rev)
    return LiveViewer(robot, config.viewer, serve=config.viewer.enabled, record_path=record_mcap, clock=clock)
