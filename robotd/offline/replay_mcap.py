"""A replay's outputs as MCAP: the log itself, robotd's filter on the live view's channels (so one Foxglove layout
serves the robot and its replays), and the other methods and the truth on channels of their own.

Topic | what
--- | ---
`/log/<type>` | the sensor log (robotd.viz.logtopics): the file replays again
`/pose`, `/pose/*`, `/tf`, `/odometry/*`, `/ips/fixes`, `/ips/verdicts` | robotd's filter, as the daemon publishes
  it (robotd.viz.channels)
`/replay/<method>/pose`, `/replay/<method>/trail` | `paper_ekf`, `gated_ekf`, `odometry` (scored runs only) and `truth`,
  in the map

Messages are stamped with the log's time (seconds from its clock's zero). Trails reach `viewer.trail_s` back, as the
live view's: each is sent whole every TRAIL_PERIOD_S, so a trail of the whole log made the file grow with the square of
the log's length (a 7-minute log's MCAP was 169 MB, nearly all trails; an hour's would have been some 10 GB).
"""

from __future__ import annotations

import math
import os
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import foxglove
from foxglove.channels import PoseInFrameChannel, PosesInFrameChannel

from robotd.config.model import RobotdConfig
from robotd.estimation import ekf
from robotd.logs.sensorlog import IpsFix, SensorLog, Truth
from robotd.offline.metrics import Trajectory
from robotd.offline.replay import ReplayResult
from robotd.viz import scene
from robotd.viz.live import verdict_of
from robotd.viz.logtopics import LogClock
from robotd.viz.player import McapPlayer
from robotd.viz.publisher import Publisher, RobotModel, Trail

TRAIL_PERIOD_S = 1.0


class _Method:
    """One method's pose and trail channels (the trail reaching trail_s back)."""

    def __init__(self, context: foxglove.Context, name: str, trajectory: Trajectory, trail_s: float) -> None:
        self.pose = PoseInFrameChannel(f"/replay/{name}/pose", context=context)
        self.trail_channel = PosesInFrameChannel(f"/replay/{name}/trail", context=context)
        self.trajectory = trajectory
        self.trail = Trail(trail_s)

    def publish(self, clock: LogClock) -> None:
        """Every pose, and the trail of the last trail_s seconds every TRAIL_PERIOD_S."""
        next_trail = -math.inf
        traj = self.trajectory
        for t, x, y, theta in zip(traj.t, traj.x, traj.y, traj.theta, strict=True):
            pose = (float(x), float(y), float(theta) if math.isfinite(theta) else 0.0)
            t_ns = clock.at(float(t))
            self.pose.log(scene.pose_in_frame(t_ns, pose), log_time=t_ns)
            self.trail.add(float(t), pose)
            if t >= next_trail:
                next_trail = float(t) + TRAIL_PERIOD_S
                self.trail_channel.log(self.trail.message(t_ns), log_time=t_ns)


def _ekf_poses(result: ReplayResult) -> Iterator[dict[str, Any]]:
    """robotd's estimates as the pose socket's messages (without the twist, which the replay does not keep)."""
    traj, placed_at = result.ekf, next((d.t for d in result.diagnostics if d.accepted), math.inf)
    covariances = result.ekf_cov.tolist()
    for k, t in enumerate(traj.t):
        yield {
            "t": float(t), "x": float(traj.x[k]), "y": float(traj.y[k]), "theta": float(traj.theta[k]),
            "vx": 0.0, "vy": 0.0, "wz": 0.0, "covariance": list(ekf.cov_full(covariances[k])),
            "fix_state": "tracking" if t >= placed_at else "initialising",
        }  # fmt: skip


def write_replay_mcap(log: SensorLog, result: ReplayResult, config: RobotdConfig, path: Path) -> Path:
    """Write the replay's MCAP file (replaced if it exists)."""
    context = foxglove.Context()
    clock = LogClock()
    robot = RobotModel(config.ekf, result.geometry, result.ips_offset, result.counts_per_rev)
    trail_s = config.viewer.trail_s
    publisher = Publisher(context, robot, clock, trail_s=trail_s, trail_period_s=TRAIL_PERIOD_S)
    baselines = (("paper_ekf", result.paper), ("gated_ekf", result.gated), ("odometry", result.odometry))
    methods = [_Method(context, name, traj, trail_s) for name, traj in baselines if len(traj)]
    truth = [(e.t, e.x, e.y, e.theta) for e in log.events if isinstance(e, Truth)]
    if truth:
        methods.append(_Method(context, "truth", Trajectory.from_samples(truth), trail_s))
    with foxglove.open_mcap(path, allow_overwrite=True, context=context):
        publisher.record(log.meta)
        poses = _ekf_poses(result)
        pending = next(poses, None)
        diagnostics = iter(result.diagnostics)
        for event in log.events:
            while pending is not None and pending["t"] < event.t:  # the estimates taken before this event
                publisher.pose(pending)
                pending = next(poses, None)
            publisher.record(event)
            if isinstance(event, IpsFix) and math.isfinite(event.x) and math.isfinite(event.y):
                diagnostic = next(diagnostics, None)  # one per finite fix, in the log's order
                publisher.verdict(event.t, event.x, event.y, *verdict_of(diagnostic))
        while pending is not None:
            publisher.pose(pending)
            pending = next(poses, None)
        for method in methods:
            method.publish(clock)
    return path


def write_and_view(
    log: SensorLog,
    result: ReplayResult,
    config: RobotdConfig,
    *,
    out: Path,
    mcap: str | None,
    view_port: int | None,
    written: list[Path],
) -> int:
    """`robotd replay --mcap/--view`: write the MCAP file (DIR/replay.mcap for --view alone), then serve it with
    playback controls until Ctrl-C; the exit status."""
    path = Path(mcap) if mcap else out / "replay.mcap"
    try:
        write_replay_mcap(log, result, config, path)
    except (OSError, RuntimeError) as error:  # the SDK says RuntimeError for a file it cannot create
        print(f"robotd replay: --mcap {path}: cannot write it: {error}", file=sys.stderr)
        return os.EX_IOERR
    print("wrote " + ", ".join(str(p) for p in [*written, path]))
    if view_port is None:
        return 0
    player = McapPlayer(path)
    try:
        port = player.serve("127.0.0.1", view_port)
    except RuntimeError as error:
        print(f"robotd replay: --view: cannot serve on 127.0.0.1:{view_port}: {error}", file=sys.stderr)
        return os.EX_UNAVAILABLE
    print(
        f"serving the replay at ws://127.0.0.1:{port}: in Foxglove, Open connection > Foxglove WebSocket; Ctrl-C stops"
    )
    stop = threading.Event()
    try:
        player.run(stop)
    except KeyboardInterrupt:
        pass
    finally:
        player.stop()
    return 0
