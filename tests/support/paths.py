"""Where the tests find the repository, its configurations and the shared recorded data."""

from __future__ import annotations

from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
SHARED = REPO.parent / "shared"
SIM_CONFIG = REPO / "config" / "sim.yaml"
ROBOT_CONFIG = REPO / "config" / "robot.yaml"
MARVELMIND_FIXTURES = SHARED / "fixtures" / "marvelmind"
LIBRSF = SHARED / "datasets" / "librsf_labyrinth_uwb"
