"""What robotd sees, turned into Foxglove messages on the channels of robotd.viz.channels. Synchronous: the daemon
calls it from the viewer's thread (robotd.viz.live), offline tools call it directly.

The odometry-only pose is dead reckoning from the wheels alone: an `Estimator` that is given the log's wheel samples
and twists but never a fix (as `robotd replay` scores odometry), so the frame tree's `odom -> base_link` is continuous.
Drawn in the map it starts where the filter placed the robot (re-placed when the filter re-seeds after a lock-out),
so that the gap between the two trails is the drift the fixes correct.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import foxglove
from foxglove.messages import Log, LogLevel, Pose, PosesInFrame

from robotd.config.model import EkfConfig
from robotd.estimation.estimator import Estimator
from robotd.kinematics import Geometry
from robotd.logs import events
from robotd.viz import frames, scene
from robotd.viz.channels import Channels, log_json
from robotd.viz.logtopics import LogClock

TRAIL_STEP_M = 0.01  # a trail keeps a pose once the robot moved this far (or turned TRAIL_STEP_RAD): no pile at rest
TRAIL_STEP_RAD = 0.05
PLACING = frozenset(("seeded", "recovered"))  # verdicts that place the position anew
LOG_LEVELS = ((40, LogLevel.Error), (30, LogLevel.Warning), (20, LogLevel.Info), (0, LogLevel.Debug))


@dataclass(frozen=True, slots=True)
class RobotModel:
    """What the publisher needs to know of the robot: the filter's settings and geometry (odometry alone)."""

    ekf: EkfConfig
    geometry: Geometry
    ips_offset_m: tuple[float, float]
    counts_per_rev: int


class Trail:
    """The poses of the last `span_s` seconds, one each TRAIL_STEP_M of travel (or TRAIL_STEP_RAD of turn), each with
    its Foxglove pose built once: a trail is sent whole, twice a second, and building thousands of poses anew each
    time cost more than everything else the viewer does."""

    def __init__(self, span_s: float) -> None:
        self.span_s = span_s
        self.poses: deque[tuple[float, frames.Pose2, Pose]] = deque()

    def add(self, t: float, pose: frames.Pose2) -> None:
        """Keep the pose if it moved since the last one kept; forget the ones older than the span."""
        poses = self.poses
        if poses:
            _, (x, y, th), _ = poses[-1]
            turned = abs(math.remainder(pose[2] - th, math.tau))
            if math.hypot(pose[0] - x, pose[1] - y) < TRAIL_STEP_M and turned < TRAIL_STEP_RAD:
                return
        poses.append((t, pose, scene.pose_message(pose)))
        while poses and poses[0][0] < t - self.span_s:
            poses.popleft()

    def clear(self) -> None:
        """Forget every pose (the odometry's drawing was re-placed)."""
        self.poses.clear()

    def message(self, t_ns: int, frame: str = scene.MAP) -> PosesInFrame:
        """The trail as one message in `frame`, stamped t_ns."""
        return scene.trail(t_ns, [built for _, _, built in self.poses], frame)


class Publisher:
    """Publishes the daemon's poses, fixes, control and log on `Channels` (see the module docstring)."""

    def __init__(
        self,
        context: foxglove.Context,
        robot: RobotModel,
        clock: LogClock,
        *,
        trail_s: float = 120.0,
        trail_period_s: float = 0.5,
    ) -> None:
        self.channels = Channels(context)
        self.robot = robot
        self.clock = clock
        self.odometry = Estimator(robot.ekf, robot.geometry, robot.ips_offset_m, robot.counts_per_rev)
        self.fused_trail = Trail(trail_s)
        self.odometry_trail = Trail(trail_s)
        self.trail_period_s = trail_period_s
        self._next_trail = -math.inf
        self._odometry_in_map: frames.Pose2 | None = None  # map <- odom, fixed where the filter placed the robot
        self._replace = True
        self.fixes = 0

    # --- inputs ------------------------------------------------------------------------------------------------

    def record(self, record: events.Record) -> None:
        """A sensor log record: on its `/log/<type>` channel; wheels and twists also drive the odometry alone."""
        self.channels.record(record, self.clock.next_record(record))
        if isinstance(record, events.Wheels):
            self.odometry.on_wheels(record.t, record.ticks)
        elif isinstance(record, events.TwistSample):
            self.odometry.on_twist(record.t, record.vx, record.vy, record.wz)

    def verdict(self, t: float, x: float, y: float, verdict: str, details: dict[str, Any]) -> None:
        """The gate's verdict on a fix at (x, y) that arrived at t (details: NIS, gate, innovation...)."""
        self.fixes += 1
        t_ns = self.clock.at(t)
        nis = details.get("nis")
        self.channels.fixes.log(
            scene.fix_marker(t_ns, self.fixes, (x, y), verdict, nis if isinstance(nis, float) else None), log_time=t_ns
        )
        log_json(self.channels.verdicts, {"t": t, "x": x, "y": y, "verdict": verdict, **details}, t_ns)
        if verdict in PLACING:
            self._replace = True

    def beacons(self, t: float, stationary: Sequence[tuple[int, float, float, float, bool]]) -> None:
        """The stationary beacons the hedgehog reported (address, x, y, z, applicable)."""
        t_ns = self.clock.at(t)
        self.channels.beacons.log(scene.beacons(t_ns, stationary), log_time=t_ns)

    def control(self, message: dict[str, Any]) -> None:
        """One control period's figures (`t` and plottable numbers)."""
        log_json(self.channels.control, message, self.clock.at(message["t"]))

    def status(self, message: dict[str, Any]) -> None:
        """The daemon's status message."""
        log_json(self.channels.status, message, self.clock.at(message["t"]))

    def log_line(self, t: float, level: int, name: str, text: str) -> None:
        """One of the daemon's log lines."""
        t_ns = self.clock.at(t)
        severity = next(severity for floor, severity in LOG_LEVELS if level >= floor)
        self.channels.log.log(Log(timestamp=scene.stamp(t_ns), level=severity, message=text, name=name), log_time=t_ns)

    def pose(self, message: dict[str, Any]) -> None:
        """A pose as the pose socket sends it: the fused pose, its ellipse, the frame tree, the odometry alone."""
        t = float(message["t"]) if message["t"] is not None else math.nan
        if not math.isfinite(t):
            return  # the daemon's pose before its first input: nowhere to draw it, no time to stamp it
        t_ns = self.clock.at(t)
        fused = (float(message["x"]), float(message["y"]), float(message["theta"]))
        cov: list[float] = message["covariance"]
        twist = (float(message["vx"]), float(message["vy"]), float(message["wz"]))
        channels = self.channels
        channels.pose.log(scene.pose_in_frame(t_ns, fused), log_time=t_ns)
        channels.pose_odometry.log(scene.odometry(t_ns, fused, twist, cov, t), log_time=t_ns)
        channels.pose_ellipse.log(scene.ellipse(t_ns, (fused[0], fused[1]), cov), log_time=t_ns)
        estimate = self.odometry.pose(t)
        odom = (estimate.x, estimate.y, estimate.theta)
        placed = message.get("fix_state") != "initialising"
        if self._odometry_in_map is None or (placed and self._replace):
            self._odometry_in_map = frames.correction(fused, odom)
            self.odometry_trail.clear()
            self._replace = not placed
        in_map = frames.compose(self._odometry_in_map, odom)
        channels.odometry_pose.log(scene.pose_in_frame(t_ns, in_map), log_time=t_ns)
        channels.tf.log(
            scene.transforms(t_ns, frames.correction(fused, odom), odom, self.robot.ips_offset_m), log_time=t_ns
        )
        self.fused_trail.add(t, fused)
        self.odometry_trail.add(t, in_map)
        if t >= self._next_trail:
            self._next_trail = t + self.trail_period_s
            channels.pose_trail.log(self.fused_trail.message(t_ns), log_time=t_ns)
            channels.odometry_trail.log(self.odometry_trail.message(t_ns), log_time=t_ns)
