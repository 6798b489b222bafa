"""What `robotd fleet` shows: every robot on the broker, one row each, from its pose and retained status (pure).

The table is rebuilt from the latest pose and status of each robot; a robot whose last will or clean exit said
`offline` stays in the table, marked so, until its retained status is deleted from the broker.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Any

from robotd.fleet import topics

COLUMNS = (
    "robot", "state", "x m", "y m", "θ °", "speed m/s", "fix age s", "fix", "odometry", "control", "stop", "faults",
    "seen s ago",
)  # fmt: skip


@dataclass
class RobotView:
    """The latest of one robot: its pose, its status, and when each arrived (the viewer's monotonic clock)."""

    pose: dict[str, Any] = field(default_factory=dict)
    status: dict[str, Any] = field(default_factory=dict)
    pose_seen: float = -math.inf
    status_seen: float = -math.inf


class FleetView:
    """The fleet as the broker shows it."""

    def __init__(self) -> None:
        self.robots: dict[str, RobotView] = {}
        self.stops: dict[str, str] = {}  # target -> "stop" or "release", from the retained orders
        self.malformed = 0

    def take(self, topic: str, payload: bytes, now: float) -> None:
        """One message of the tree (others and bad JSON are counted and ignored)."""
        place = topics.split(topic)
        if place is None:
            return
        name, leaf = place
        if not payload:  # a deleted retained message
            if leaf == "stop":
                self.stops.pop(name, None)
            return
        try:
            message = json.loads(payload)
        except (ValueError, UnicodeDecodeError):
            self.malformed += 1
            return
        if not isinstance(message, dict):
            self.malformed += 1
            return
        if leaf == "stop":
            self.stops[name] = str(message.get("action", "?"))
            return
        if name == topics.FLEET:
            return
        robot = self.robots.setdefault(name, RobotView())
        if leaf == "pose":
            robot.pose, robot.pose_seen = message, now
        elif leaf == "status":
            robot.status, robot.status_seen = message, now

    def rows(self, now: float) -> list[tuple[str, ...]]:
        """One row of COLUMNS per robot, by name."""
        return [self._row(name, robot, now) for name, robot in sorted(self.robots.items())]

    def _row(self, name: str, robot: RobotView, now: float) -> tuple[str, ...]:
        pose, status = robot.pose, robot.status
        speed = math.hypot(_number(pose.get("vx")), _number(pose.get("vy"))) if pose else math.nan
        stop = status.get("stop", {}) if isinstance(status.get("stop"), dict) else {}
        held = "HELD" if stop.get("held") else ("-" if status else "?")
        faults = status.get("faults") or []
        seen = max(robot.pose_seen, robot.status_seen)
        return (
            name,
            str(status.get("state", "?")),
            _fmt(pose.get("x"), 2),
            _fmt(pose.get("y"), 2),
            _fmt(math.degrees(_number(pose.get("theta"))), 0),
            _fmt(speed, 2),
            _fmt(pose.get("fix_age_s"), 2),
            str(pose.get("fix_state", status.get("fix", "?"))),
            str(pose.get("odometry_state", status.get("odometry", "?"))),
            str(status.get("control", "?")),
            held,
            ",".join(str(fault.get("kind", "?")) for fault in faults if isinstance(fault, dict)) or "-",
            _fmt(now - seen, 1),
        )

    def render(self, now: float, broker: str) -> str:
        """The table as text, with a heading line naming the broker and the fleet-wide stop."""
        fleet_stop = self.stops.get(topics.FLEET)
        heading = f"robotd fleet on {broker}: {len(self.robots)} robot(s)"
        if fleet_stop == "stop":
            heading += "; FLEET STOP retained (robotd fleet release --all)"
        rows = [COLUMNS, *self.rows(now)]
        widths = [max(len(row[i]) for row in rows) for i in range(len(COLUMNS))]
        lines = ["  ".join(cell.rjust(width) for cell, width in zip(row, widths, strict=True)) for row in rows]
        return "\n".join([heading, *lines])


def _number(value: object) -> float:
    return float(value) if isinstance(value, int | float) else math.nan


def _fmt(value: object, digits: int) -> str:
    number = _number(value)
    return "-" if not math.isfinite(number) else f"{number:.{digits}f}"
