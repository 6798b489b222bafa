"""The fleet's MQTT topic tree: one subtree per robot, one fleet-wide stop.

```
robotd/<robot_id>/pose     the pose stream's pose message (JSON), QoS 0, at fleet.pose_rate_hz
robotd/<robot_id>/status   retained: {"state": "online", ...}; the broker's last will {"state": "offline"}
robotd/<robot_id>/stop     retained: a signed stop or release for this robot
robotd/fleet/stop          retained: a signed stop or release for every robot
```
"""

from __future__ import annotations

ROOT = "robotd"
FLEET = "fleet"  # the stop target meaning every robot (never a robot id: see robotd.config.fleet)
FLEET_STOP = f"{ROOT}/{FLEET}/stop"
ALL_POSES = f"{ROOT}/+/pose"
ALL_STATUSES = f"{ROOT}/+/status"
ALL_STOPS = f"{ROOT}/+/stop"


def pose(robot_id: str) -> str:
    """The robot's pose topic."""
    return f"{ROOT}/{robot_id}/pose"


def status(robot_id: str) -> str:
    """The robot's retained status topic (and its last will)."""
    return f"{ROOT}/{robot_id}/status"


def stop(target: str) -> str:
    """The retained stop topic of a robot, or of the whole fleet for FLEET."""
    return f"{ROOT}/{target}/stop"


def split(topic: str) -> tuple[str, str] | None:
    """(robot id or FLEET, leaf) of a topic in the tree, else None."""
    parts = topic.split("/")
    if len(parts) != 3 or parts[0] != ROOT:
        return None
    return parts[1], parts[2]
