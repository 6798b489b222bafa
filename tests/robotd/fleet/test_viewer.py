"""The fleet table, from messages as the broker delivers them."""

from __future__ import annotations

import json
from collections.abc import Mapping

from robotd.fleet.viewer import COLUMNS, FleetView


def encode(message: Mapping[str, object]) -> bytes:
    return json.dumps(message).encode()


def test_rows_show_pose_status_stop_and_faults() -> None:
    view = FleetView()
    pose = {"x": 1.234, "y": -0.5, "theta": 1.5708, "vx": 0.3, "vy": 0.4, "fix_age_s": 0.12, "fix_state": "tracking",
            "odometry_state": "ok"}  # fmt: skip
    view.take("robotd/b/pose", encode(pose), 10.0)
    status = {"state": "online", "control": "fault", "faults": [{"kind": "stall"}], "stop": {"held": True}}
    view.take("robotd/b/status", encode(status), 10.5)
    view.take("robotd/a/status", encode({"state": "offline"}), 9.0)
    view.take("robotd/fleet/stop", encode({"action": "stop"}), 9.0)
    view.take("robotd/a/pose", b"not json", 9.0)
    view.take("elsewhere/x/pose", encode(pose), 9.0)
    rows = view.rows(11.0)
    assert [row[0] for row in rows] == ["a", "b"]
    b = dict(zip(COLUMNS, rows[1], strict=True))
    assert (b["state"], b["x m"], b["y m"], b["θ °"], b["speed m/s"]) == ("online", "1.23", "-0.50", "90", "0.50")
    assert (b["fix age s"], b["fix"], b["odometry"], b["control"]) == ("0.12", "tracking", "ok", "fault")
    assert (b["stop"], b["faults"], b["seen s ago"]) == ("HELD", "stall", "0.5")
    a = dict(zip(COLUMNS, rows[0], strict=True))
    assert (a["state"], a["x m"]) == ("offline", "-")
    assert view.malformed == 1
    text = view.render(11.0, "mqtt://127.0.0.1:1883")
    assert "2 robot(s); FLEET STOP retained" in text.splitlines()[0]


def test_a_deleted_retained_stop_leaves_the_table() -> None:
    view = FleetView()
    view.take("robotd/fleet/stop", encode({"action": "stop"}), 1.0)
    view.take("robotd/fleet/stop", b"", 2.0)
    assert view.stops == {}
    assert "FLEET STOP" not in view.render(2.0, "mqtt://h:1")
