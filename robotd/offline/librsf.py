"""Convert the libRSF "Labyrinth" indoor UWB dataset (CSV folder) to a robotd sensor log.

The dataset (CC BY-SA 4.0, (c) 2017-2023 Tim Pfeifer, TU Chemnitz) is a differential-drive robot with real UWB ranges,
wheel speeds and 2D ground truth. robotd reads it as:
- `twist` events from the wheel speeds, with libRSF's convention (col3 = v - b w, col4 = v + b w, b = 0.0785 m a
  half track): v = (c3 + c4) / 2, w = (c4 - c3) / (2 b), vy = 0;
- `ips` fixes from `derived_multilateration_fixes.csv` (multilateration of the ranges), measured at their time stamp;
- `truth` from `ground_truth.csv`, without heading (NaN: the dataset has none).
The converted log's meta keeps the attribution, as the licence requires.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

from robotd.logs.sensorlog import Event, IpsFix, LogWriter, Meta, Truth, TwistSample

HALF_TRACK_M = 0.0785
ATTRIBUTION = (
    "libRSF Labyrinth indoor UWB dataset, (c) 2017-2023 Tim Pfeifer (TU Chemnitz), CC BY-SA 4.0 "
    "(github.com/TUC-ProAut/libRSF datasets/Indoor_UWB); converted by robotd.offline.librsf: twist from wheel speeds "
    "v=(c3+c4)/2, w=(c4-c3)/(2*0.0785); ips from derived_multilateration_fixes.csv; truth without heading"
)


class DatasetError(Exception):
    """The folder is not the libRSF dataset as expected."""


def _rows(path: Path) -> list[dict[str, str]]:
    try:
        with open(path, encoding="utf-8", newline="") as stream:
            return list(csv.DictReader(stream))
    except OSError as error:
        raise DatasetError(f"{path}: cannot read: {error}") from None


def _value(row: dict[str, str], key: str, path: Path, number: int) -> float:
    try:
        return float(row[key])
    except (KeyError, TypeError, ValueError):
        raise DatasetError(f"{path}: row {number}: column '{key}' missing or not a number") from None


def convert(folder: Path) -> tuple[Meta, list[Event]]:
    """The dataset in `folder` as a meta and events in time order."""
    events: list[tuple[float, int, Event]] = []
    odometry = folder / "wheel_odometry.csv"
    for n, row in enumerate(_rows(odometry), start=2):
        t = _value(row, "t_s", odometry, n)
        c3 = _value(row, "v_right_wheel_mps", odometry, n)  # libRSF's column 3: v - b w, whatever its header says
        c4 = _value(row, "v_left_wheel_mps", odometry, n)
        v, w = 0.5 * (c3 + c4), (c4 - c3) / (2.0 * HALF_TRACK_M)
        events.append((t, 0, TwistSample(t, v, 0.0, w)))
    fixes = folder / "derived_multilateration_fixes.csv"
    for n, row in enumerate(_rows(fixes), start=2):
        t = _value(row, "t_s", fixes, n)
        events.append((t, 1, IpsFix(t, _value(row, "x_m", fixes, n), _value(row, "y_m", fixes, n), 0.0, t)))
    truth = folder / "ground_truth.csv"
    for n, row in enumerate(_rows(truth), start=2):
        t = _value(row, "t_s", truth, n)
        events.append((t, 2, Truth(t, _value(row, "x_m", truth, n), _value(row, "y_m", truth, n), math.nan)))
    if not events:
        raise DatasetError(f"{folder}: no events")
    events.sort(key=lambda item: (item[0], item[1]))
    meta = Meta(robot={"ips_offset": [0.0, 0.0]}, source=ATTRIBUTION)
    return meta, [event for _, _, event in events]


def write(folder: Path, out: Path) -> int:
    """Convert the dataset in `folder` to the log file `out` (its folder made if missing); returns the number of
    events."""
    meta, events = convert(folder)
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out, "w", encoding="utf-8") as stream:
        writer = LogWriter(stream, meta)
        for event in events:
            writer.write(event)
    return len(events)


__all__ = ["ATTRIBUTION", "DatasetError", "convert", "write"]
