"""The fleet as Foxglove sees it: every robot's MQTT pose and status turned into messages on its own channels.

Each robot gets its channels when its first message arrives (the SDK advertises them to connected viewers then):

Topic | schema | what
--- | --- | ---
`/<id>/pose` | foxglove.PoseInFrame | the robot's fused pose in the shared `map` frame
`/<id>/pose/ellipse` | foxglove.SceneUpdate | the 95 % covariance ellipse of its position
`/<id>/pose/trail` | foxglove.PosesInFrame | where it has been (the last `trail_s` seconds)
`/<id>/status` | JSON | `state` (online/offline), `stop_held`, `faults`, and its retained status as the broker has it
`/<id>/label` | foxglove.SceneUpdate | its name and what is wrong (offline, STOP, fault kinds) above `<id>/base_link`
`/tf` | foxglove.FrameTransforms | map -> `<id>/base_link` for every robot

Messages are stamped with the viewer's receive time: the robots' own clocks are other machines' clocks, and one time
line keeps the frame tree and the 3D panel consistent across robots (the robot's `t` and `stamp` stay in its status).
Geometry comes from robotd.viz (scene, frames, Trail); nothing here draws on its own. Synchronous, no I/O.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import foxglove
from foxglove.channels import FrameTransformsChannel, PoseInFrameChannel, PosesInFrameChannel, SceneUpdateChannel
from foxglove.messages import FrameTransforms

from robotd.fleet import topics
from robotd.viz import scene
from robotd.viz.channels import log_json
from robotd.viz.publisher import Trail

TF = "/tf"


def robot_topic(robot_id: str, leaf: str = "") -> str:
    """A robot's Foxglove topic: `/<id>` and `leaf` (e.g. "pose/ellipse")."""
    return f"/{robot_id}/{leaf}" if leaf else f"/{robot_id}"


def base_link(robot_id: str) -> str:
    """The robot's body frame in the fleet's frame tree."""
    return f"{robot_id}/{scene.BASE_LINK}"


@dataclass
class RobotChannels:
    """One robot's channels and trail."""

    pose: PoseInFrameChannel
    ellipse: SceneUpdateChannel
    trail: PosesInFrameChannel
    status: foxglove.Channel
    label: SceneUpdateChannel
    poses: Trail
    next_trail: float = -math.inf


class FleetScene:
    """Takes the broker's messages of the robotd tree and publishes each robot on its channels of `context`."""

    def __init__(
        self,
        context: foxglove.Context,
        *,
        trail_s: float = 120.0,
        trail_period_s: float = 0.5,
        clock_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        self.context = context
        self.tf = FrameTransformsChannel(TF, context=context)
        self.robots: dict[str, RobotChannels] = {}
        self.trail_s = trail_s
        self.trail_period_s = trail_period_s
        self._clock_ns = clock_ns
        self.messages = 0  # poses and statuses published
        self.malformed = 0  # payloads that are not a JSON object
        self.skipped = 0  # poses that cannot be drawn (a field missing or not a number)

    def take(self, topic: str, payload: bytes) -> None:
        """One message of the tree: a robot's pose or status is published on its channels; the rest is ignored."""
        place = topics.split(topic)
        if place is None or place[0] == topics.FLEET or place[1] not in ("pose", "status") or not payload:
            return  # orders, other trees, deleted retained messages: nothing to draw
        name, leaf = place
        try:
            message = json.loads(payload)
        except (ValueError, UnicodeDecodeError):
            message = None
        if not isinstance(message, dict):
            self.malformed += 1
            return
        t_ns = self._clock_ns()
        if leaf == "pose" and not self._pose(name, message, t_ns):
            self.skipped += 1
            return
        if leaf == "status":
            summary = status_summary(name, message)
            channels = self._channels(name)
            log_json(channels.status, summary, t_ns)
            text, rgba = label_of(summary)
            channels.label.log(scene.label(t_ns, "name", text, base_link(name), rgba), log_time=t_ns)
        self.messages += 1

    def _channels(self, name: str) -> RobotChannels:
        channels = self.robots.get(name)
        if channels is None:
            context = self.context
            channels = RobotChannels(
                pose=PoseInFrameChannel(robot_topic(name, "pose"), context=context),
                ellipse=SceneUpdateChannel(robot_topic(name, "pose/ellipse"), context=context),
                trail=PosesInFrameChannel(robot_topic(name, "pose/trail"), context=context),
                status=foxglove.Channel(robot_topic(name, "status"), message_encoding="json", context=context),
                label=SceneUpdateChannel(robot_topic(name, "label"), context=context),
                poses=Trail(self.trail_s),
            )
            self.robots[name] = channels
        return channels

    def _pose(self, name: str, message: dict[str, Any], t_ns: int) -> bool:
        """Publish the pose, its ellipse, the robot's frame and trail; False when the pose cannot be drawn."""
        try:
            pose = (float(message["x"]), float(message["y"]), float(message["theta"]))
            cov = [float(value) for value in message["covariance"]]
        except (KeyError, TypeError, ValueError):
            return False
        if len(cov) != 9 or not all(math.isfinite(value) for value in (*pose, *cov)):
            return False
        channels = self._channels(name)
        channels.pose.log(scene.pose_in_frame(t_ns, pose), log_time=t_ns)
        channels.ellipse.log(scene.ellipse(t_ns, (pose[0], pose[1]), cov), log_time=t_ns)
        self.tf.log(
            FrameTransforms(transforms=[scene.frame_transform(t_ns, scene.MAP, base_link(name), pose)]),
            log_time=t_ns,
        )
        t = t_ns * 1e-9
        channels.poses.add(t, pose)
        if t >= channels.next_trail:
            channels.next_trail = t + self.trail_period_s
            channels.trail.log(channels.poses.message(t_ns), log_time=t_ns)
        return True


def status_summary(name: str, status: dict[str, Any]) -> dict[str, Any]:
    """What a viewer plots or tabulates of a robot's retained status: state, stop held, fault kinds, and the status."""
    stop = status.get("stop")
    faults = status.get("faults")
    return {
        "robot_id": name,
        "state": str(status.get("state", "?")),
        "online": status.get("state") == "online",
        "stop_held": isinstance(stop, dict) and bool(stop.get("held", False)),
        "faults": [str(f.get("kind", "?")) for f in faults if isinstance(f, dict)] if isinstance(faults, list) else [],
        "status": status,
    }


OFFLINE_COLOUR = (0.5, 0.5, 0.5, 0.8)
ALARM_COLOUR = (0.95, 0.15, 0.1, 1.0)


def label_of(summary: dict[str, Any]) -> tuple[str, tuple[float, float, float, float]]:
    """A robot's label and its colour from its status summary: grey offline, red stopped or faulty."""
    words = [str(summary["robot_id"])]
    if not summary["online"]:
        words.append(str(summary["state"]))
    if summary["stop_held"]:
        words.append("STOP")
    words.extend(summary["faults"])
    if not summary["online"]:
        return " ".join(words), OFFLINE_COLOUR
    return " ".join(words), ALARM_COLOUR if len(words) > 1 else scene.FUSED_COLOUR
