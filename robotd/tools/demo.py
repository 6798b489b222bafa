"""`robotd demo`: the virtual robot and the daemon as separate processes, the paper's square driven over UDP teleop.

Theory of operation. The demo writes a private copy of the simulation config (free loopback ports, paths inside its
output folder, so demos and tests never collide), starts `robotd vhw` and `robotd run --record` as child processes,
records the pose stream from the daemon's Unix socket, and drives the square open-loop with the teleop client, as
the paper's remote control did. At the end it stops both children (SIGTERM, then SIGKILL after a grace period: every
child is reaped on every way out), joins the daemon's sensor log with the simulator's ground truth,
scores the live pose stream (robotd's EKF as it ran) and replays the log for odometry alone, the raw fixes and the
paper's EKF, then writes the figures and the results table.

No process is left behind. The children run in their own process group, so a terminal's Ctrl-C or hang-up reaches
the parent only, and `stop_signals()` turns SIGINT, SIGTERM, SIGHUP and SIGQUIT into an exception: the parent stops them
in order, the daemon first (it zeroes the motors while the virtual pigpiod still listens), then the virtual robot.
Should the parent die without running any of that (SIGKILL), each child gets SIGTERM from the kernel
(robotd.tools.childguard). The daemon is waited for until its pose socket accepts a connection, not until the socket
file exists: a killed run leaves the file behind.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import Any, TextIO

import yaml

from robotd.config.model import RobotdConfig, load
from robotd.daemon import poseclient
from robotd.kinematics import Twist
from robotd.logs import sensorlog
from robotd.tools.teleop_client import Leg, UdpLink, run_plan, square_plan

GRACE_S = 3.0
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT)


class StopRequested(Exception):  # noqa: N818 - a request, not an error
    """A stop signal arrived; raised where the main thread was, so every `finally` on the way out runs."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


@contextlib.contextmanager
def stop_signals() -> Iterator[None]:
    """Raise StopRequested on the first of STOP_SIGNALS; later ones are ignored, so that they cannot cut the
    stopping of the children short (which is bounded: GRACE_S per child, then SIGKILL)."""
    requested: list[int] = []

    def on_signal(signum: int, _frame: FrameType | None) -> None:
        if not requested:
            requested.append(signum)
            raise StopRequested(signum)

    previous = {signum: signal.signal(signum, on_signal) for signum in STOP_SIGNALS}
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


@dataclass(frozen=True, slots=True)
class DemoPlan:
    """What the demo drives."""

    loops: int = 1
    side_m: float = 3.0
    speed_mps: float = 0.3
    pause_s: float = 1.0
    seed: int | None = None


def _free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def free_tcp_port() -> int:
    """A TCP port on loopback that nobody holds right now."""
    return _free_port(socket.SOCK_STREAM)


def private_config(base: Path, out: Path, overrides: dict[str, dict[str, Any]] | None = None) -> Path:
    """A copy of `base` with free loopback ports, every path inside `out` and some keys of some sections changed."""
    raw: dict[str, Any] = yaml.safe_load(base.read_text(encoding="utf-8")) or {}
    raw.setdefault("pigpiod", {})["port"] = _free_port(socket.SOCK_STREAM)
    raw.setdefault("marvelmind", {})["device"] = str(out / "marvelmind")
    teleop = raw.setdefault("teleop", {})
    teleop.update({"bind": "127.0.0.1", "port": _free_port(socket.SOCK_DGRAM)})
    raw.setdefault("pose_socket", {})["path"] = str(out / "pose.sock")
    raw.setdefault("sim", {})["record_path"] = str(out / "truth.jsonl")
    for section, values in (overrides or {}).items():
        raw.setdefault(section, {}).update(values)
    path = out / "config.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False), encoding="utf-8")
    load(path)  # the copy must be as valid as the original
    return path


class Children:
    """Child processes that are always stopped and reaped, whatever happens."""

    def __init__(self) -> None:
        self.procs: list[subprocess.Popen[str]] = []
        self.names: dict[int, str] = {}

    def start(self, name: str, args: list[str], log_path: Path) -> subprocess.Popen[str]:
        """Start `robotd ARGS` with its output in `log_path`."""
        log = log_path.open("w", encoding="utf-8")
        # Its own process group: a terminal's Ctrl-C and hang-up reach the parent only, which stops the children in
        # order. Not its own session: that would also put it in its own scheduler autogroup, where, on a loaded
        # machine, the daemon and the virtual robot were measured to stall for up to 1.5 s (0.3 s in the same one).
        proc = subprocess.Popen(  # noqa: S603 - our own interpreter running our own module
            [sys.executable, "-m", "robotd.tools.childguard", str(os.getpid()), *args],
            stdin=subprocess.DEVNULL,  # a background process group must not read the terminal
            stdout=log,
            stderr=subprocess.STDOUT,
            text=True,
            process_group=0,
        )
        log.close()
        self.names[proc.pid] = name
        self.procs.append(proc)
        return proc

    def stop(self, proc: subprocess.Popen[str]) -> int:
        """SIGTERM, then SIGKILL after a grace period; returns the exit status."""
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(GRACE_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        return proc.returncode

    def stop_all(self) -> list[tuple[str, int]]:
        """Stop every child, last started first (the daemon before the virtual robot); their names and statuses.

        A stop signal that arrives meanwhile is raised once all are stopped, not in the middle."""
        statuses: list[tuple[str, int]] = []
        request: StopRequested | None = None
        for proc in reversed(self.procs):
            while True:
                try:
                    statuses.append((self.names[proc.pid], self.stop(proc)))
                    break
                except StopRequested as interruption:  # (only the first signal raises: this happens once at most)
                    request = interruption
        if request is not None:
            raise request
        return statuses


def _wait_for(condition: Callable[[], bool], timeout_s: float, what: str, children: Children) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        for proc in children.procs:
            if proc.poll() is not None:
                name = children.names[proc.pid]
                raise RuntimeError(f"{name} exited with status {proc.returncode} while waiting for {what}")
        if time.monotonic() > deadline:
            raise RuntimeError(f"timed out after {timeout_s:g} s waiting for {what}")
        time.sleep(0.05)


class PoseRecorder(threading.Thread):
    """Reads the daemon's pose socket and appends every pose message to a JSON Lines file."""

    def __init__(self, path: Path, out: Path) -> None:
        """Connect to the pose socket (OSError when nobody accepts there)."""
        super().__init__(name="pose-recorder", daemon=True)
        self.sock = poseclient.connect(str(path))
        self.out = out
        self.latest: dict[str, Any] | None = None
        self.count = 0

    def run(self) -> None:
        """Copy pose lines until the daemon closes the socket."""
        with self.out.open("w", encoding="utf-8") as out:
            for received in poseclient.messages(self.sock):
                if received.kind == "pose":
                    out.write(received.line)
                    self.latest = received.message
                    self.count += 1

    def close(self) -> None:
        """Stop reading."""
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)
        self.sock.close()
        self.join(GRACE_S)


def merged_log(run_log: Path, truth_log: Path, out: Path) -> Path:
    """The daemon's sensor log with the simulator's truth events, sorted by arrival time."""
    run = sensorlog.read_log(run_log)
    truth = [e for e in sensorlog.read_log(truth_log).events if isinstance(e, sensorlog.Truth)]
    events = sorted([*run.events, *truth], key=lambda e: e.t)  # stable: same-time events keep their order
    with out.open("w", encoding="utf-8") as stream:
        writer = sensorlog.LogWriter(stream, sensorlog.Meta(run.meta.robot, "robotd demo: daemon log + vhw truth"))
        for event in events:
            writer.write(event)
    return out


def _progress(out: TextIO, started: float, legs: list[Leg]) -> Callable[[Leg], None]:
    index = 0

    def report(leg: Leg) -> None:
        nonlocal index
        index += 1
        what = "stop" if leg.twist == Twist(0.0, 0.0, 0.0) else f"vx {leg.twist.vx:+.2f} vy {leg.twist.vy:+.2f}"
        out.write(f"\rrobotd demo: {time.monotonic() - started:5.1f} s, leg {index}/{len(legs)}: {what:24s}")
        out.flush()

    return report


@contextlib.contextmanager
def running_robot(
    config_path: Path, out: Path, seed: int | None, stopped: list[tuple[str, int]] | None = None
) -> Iterator[tuple[Children, PoseRecorder]]:
    """The virtual robot and the daemon running, with a pose recorder attached; all stopped on exit (their names and
    exit statuses, in the order they were stopped, appended to `stopped`)."""
    config = load(config_path)
    children = Children()
    recorder: PoseRecorder | None = None
    device = Path(config.marvelmind.device)
    if device.is_symlink():  # a killed run's link (the private config puts it in `out`): wait for the new one
        device.unlink()
    try:
        seed_args = [] if seed is None else ["--seed", str(seed)]
        children.start("robotd vhw", ["vhw", "--config", str(config_path), *seed_args], out / "vhw.log")
        _wait_for(device.exists, 20.0, "the virtual robot", children)
        # the demo replaces its own outputs: the daemon never overwrites a log, it would record to run.1.jsonl
        (out / "run.jsonl").unlink(missing_ok=True)
        (out / "run.mcap").unlink(missing_ok=True)  # the run as MCAP too: the log and what the daemon published
        children.start(
            "robotd run",
            [
                "run",
                "--config",
                str(config_path),
                "--record",
                str(out / "run.jsonl"),
                "--record",
                str(out / "run.mcap"),
            ],
            out / "daemon.log",
        )

        def attach() -> bool:
            nonlocal recorder
            with contextlib.suppress(OSError):  # no file yet, or a killed run's file nobody listens on
                recorder = PoseRecorder(Path(config.pose_socket.path), out / "poses.jsonl")
            return recorder is not None

        _wait_for(attach, 20.0, "the daemon's pose socket to accept", children)
        assert recorder is not None
        recorder.start()
        _wait_for(lambda: recorder is not None and recorder.count > 0, 10.0, "the first pose", children)
        yield children, recorder
    finally:
        statuses = children.stop_all()
        if stopped is not None:
            stopped.extend(statuses)
        if recorder is not None:
            recorder.close()


def drive(config_path: Path, plan: DemoPlan, out: TextIO) -> None:
    """Drive the square through the UDP teleop client, open-loop."""
    config: RobotdConfig = load(config_path)
    legs = square_plan(plan.side_m, plan.speed_mps, plan.loops, plan.pause_s)
    legs.append(Leg(Twist(0.0, 0.0, 0.0), 1.5))  # come to rest before the end
    link = UdpLink("127.0.0.1", config.teleop.port, None)
    try:
        if not link.sync(5.0):
            raise RuntimeError("the daemon did not answer the teleop client's hello within 5 s")
        run_plan(link, legs, 20.0, report=_progress(out, time.monotonic(), legs))
    finally:
        link.close()
    out.write("\n")


def run_demo(base_config: Path, out_dir: Path, plan: DemoPlan, out: TextIO = sys.stdout) -> dict[str, Any]:
    """Run the whole demo; returns the metrics and writes figures and table into `out_dir`."""
    from robotd.offline.demo_report import report  # noqa: PLC0415 - plotting is only needed at the end

    out_dir.mkdir(parents=True, exist_ok=True)
    config_path = private_config(base_config, out_dir.resolve())
    started = time.monotonic()
    with running_robot(config_path, out_dir, plan.seed) as (children, _recorder):
        out.write(f"robotd demo: virtual robot and daemon up in {time.monotonic() - started:.1f} s; driving\n")
        drive(config_path, plan, out)
        daemon = children.procs[-1]
        status = children.stop(daemon)
        if status != 0:
            raise RuntimeError(f"the daemon exited with status {status}: see {out_dir / 'daemon.log'}")
    merged = merged_log(out_dir / "run.jsonl", out_dir / "truth.jsonl", out_dir / "log.jsonl")
    metrics = report(merged, out_dir / "poses.jsonl", out_dir, load(config_path), out)
    out.write(f"robotd demo: the run as MCAP: {out_dir / 'run.mcap'} (open it in Foxglove: see the README)\n")
    out.write(f"robotd demo: done in {time.monotonic() - started:.1f} s; results in {out_dir}\n")
    return metrics
