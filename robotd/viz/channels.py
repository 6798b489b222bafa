"""The channels robotd publishes to Foxglove (live server, MCAP file), created on one SDK context.

Topic | schema | what
--- | --- | ---
`/pose` | foxglove.PoseInFrame | the fused pose (map)
`/pose/odometry` | foxglove.Odometry | the fused pose with its covariance (x, y, yaw of the 6x6) and twist
`/pose/ellipse` | foxglove.SceneUpdate | the 95 % covariance ellipse of the position
`/pose/trail` | foxglove.PosesInFrame | where the fused pose has been
`/odometry/pose`, `/odometry/trail` | PoseInFrame, PosesInFrame | dead reckoning alone, drawn from where the filter
  placed the robot, so its drift shows
`/tf` | foxglove.FrameTransforms | map -> odom -> base_link -> beacon
`/ips/fixes` | foxglove.SceneUpdate | each fix, coloured by the gate's verdict
`/ips/verdicts` | JSON | each fix's verdict, NIS, gate, innovation (plots)
`/beacons` | foxglove.SceneUpdate | the stationary beacons of the map, when the hedgehog reports them
`/control` | JSON | wheel speed set points and measurements (rad/s), duties, the control period (plots)
`/daemon/status` | JSON | the pose socket's status message (driver counters, filter counters)
`/daemon/log` | foxglove.Log | the daemon's log lines
`/log/<type>` | JSON | the sensor log's records (robotd.viz.logtopics), one channel per record type
"""

from __future__ import annotations

import json
import math
from typing import Any

import foxglove
from foxglove.channels import (
    FrameTransformsChannel,
    LogChannel,
    OdometryChannel,
    PoseInFrameChannel,
    PosesInFrameChannel,
    SceneUpdateChannel,
)

from robotd.logs import events
from robotd.viz import logtopics

POSE = "/pose"
POSE_ODOMETRY = "/pose/odometry"
POSE_ELLIPSE = "/pose/ellipse"
POSE_TRAIL = "/pose/trail"
ODOMETRY_POSE = "/odometry/pose"
ODOMETRY_TRAIL = "/odometry/trail"
TF = "/tf"
FIXES = "/ips/fixes"
VERDICTS = "/ips/verdicts"
BEACONS = "/beacons"
CONTROL = "/control"
STATUS = "/daemon/status"
LOG = "/daemon/log"


class Channels:
    """Every channel of the live view and recordings, on `context` (each sink of the context gets them all)."""

    def __init__(self, context: foxglove.Context) -> None:
        self.pose = PoseInFrameChannel(POSE, context=context)
        self.pose_odometry = OdometryChannel(POSE_ODOMETRY, context=context)
        self.pose_ellipse = SceneUpdateChannel(POSE_ELLIPSE, context=context)
        self.pose_trail = PosesInFrameChannel(POSE_TRAIL, context=context)
        self.odometry_pose = PoseInFrameChannel(ODOMETRY_POSE, context=context)
        self.odometry_trail = PosesInFrameChannel(ODOMETRY_TRAIL, context=context)
        self.tf = FrameTransformsChannel(TF, context=context)
        self.fixes = SceneUpdateChannel(FIXES, context=context)
        self.beacons = SceneUpdateChannel(BEACONS, context=context)
        self.log = LogChannel(LOG, context=context)
        self.verdicts = _json_channel(VERDICTS, context)
        self.control = _json_channel(CONTROL, context)
        self.status = _json_channel(STATUS, context)
        self.records = {
            tag: foxglove.Channel(
                topic.topic,
                schema=foxglove.Schema(
                    name=topic.schema_name, encoding="jsonschema", data=json.dumps(topic.schema).encode()
                ),
                message_encoding=logtopics.ENCODING,
                context=context,
            )
            for tag, topic in logtopics.record_topics().items()
        }

    def record(self, record: events.Record, log_time: int) -> None:
        """One sensor log record on its `/log/<type>` channel."""
        self.records[logtopics.tag_of(record)].log(logtopics.payload(record), log_time=log_time)


def _json_channel(topic: str, context: foxglove.Context) -> foxglove.Channel:
    return foxglove.Channel(topic, message_encoding="json", context=context)


def log_json(channel: foxglove.Channel, message: dict[str, Any], log_time: int) -> None:
    """A JSON message (NaN and infinities become null: JSON has none)."""
    channel.log(json.dumps(_finite(message)).encode(), log_time=log_time)


def _finite(value: Any) -> Any:
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {key: _finite(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(item) for item in value]
    return value
