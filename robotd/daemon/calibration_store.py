"""The learnt odometry calibration kept across restarts, in the unit's StateDirectory (ekf.calibration_file).

A robot starts calibrated: the daemon loads the file at start (a missing file: the configuration's starting values;
a damaged one: one WARNING line, and the configuration's values), saves it when a calibration window changed it (at
most once a minute) and on its way out. Writes go to a temporary file renamed over the old one, so a crash never
leaves half a file. The uncertainty is saved too, widened on load by the time the file lay unused (bounded), so a
robot changed while the daemon was stopped is found out again.
"""

from __future__ import annotations

import json
import logging
import math
import os
from pathlib import Path

from robotd.estimation.calibration import Calibration

log = logging.getLogger(__name__)
SAVE_EVERY_S = 60.0
FORMAT = "robotd-calibration"
MIN_SCALE_SIGMA = 0.02  # a saved calibration is trusted at most this much on load: the robot may have changed
MIN_LATENCY_SIGMA_S = 0.02


def load(path: str) -> Calibration | None:
    """The saved calibration, or None (no path, no file, or a damaged file: said once at WARNING)."""
    if not path:
        return None
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
        if data.get("format") != FORMAT:
            raise ValueError(f"not a {FORMAT} file")
        values = [float(data[key]) for key in ("kx", "ky", "kw", "latency_s", "time_error_s")]
        sigmas = [float(value) for value in data["sigmas"]]
        if len(sigmas) != 5 or not all(math.isfinite(v) for v in values + sigmas):
            raise ValueError("values must be 5 finite numbers and 5 sigmas")
    except FileNotFoundError:
        return None
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as error:
        log.warning("calibration file %s unusable (%s): starting from the configuration", path, error)
        return None
    floors = (MIN_SCALE_SIGMA, MIN_SCALE_SIGMA, MIN_SCALE_SIGMA, MIN_LATENCY_SIGMA_S, MIN_LATENCY_SIGMA_S)
    widened = tuple(max(s, f) for s, f in zip(sigmas, floors, strict=True))
    kx, ky, kw, latency, time_error = values
    sigmas_out = (widened[0], widened[1], widened[2], widened[3], widened[4])
    return Calibration(kx, ky, kw, latency, time_error, sigmas_out, int(data.get("windows", 0)))


def save(path: str, calibration: Calibration) -> None:
    """Write the calibration atomically (OSError: the caller says so and runs on)."""
    c = calibration
    text = json.dumps(
        {
            "format": FORMAT,
            "kx": c.kx,
            "ky": c.ky,
            "kw": c.kw,
            "latency_s": c.latency_s,
            "time_error_s": c.time_error_s,
            "sigmas": list(c.sigmas),
            "windows": c.windows,
        }
    )
    target = Path(path)
    temporary = target.with_name(target.name + ".tmp")
    temporary.write_text(text + "\n", encoding="utf-8")
    os.replace(temporary, target)


class CalibrationKeeper:
    """Saves the estimator's calibration when it changed, at most every SAVE_EVERY_S, and once more at the end."""

    def __init__(self, path: str) -> None:
        self.path = path
        self._saved_windows = -1
        self._saved_at = -math.inf
        self.failures = 0

    def maybe_save(self, calibration: Calibration, now: float, *, force: bool = False) -> None:
        """Save if the calibration has new windows and it is time (or `force`); a failed write is one WARNING."""
        if not self.path or calibration.windows == self._saved_windows:
            return
        if not force and now - self._saved_at < SAVE_EVERY_S:
            return
        try:
            save(self.path, calibration)
        except OSError as error:
            self.failures += 1
            log.warning("cannot save the calibration to %s: %s", self.path, error)
        else:
            self._saved_windows = calibration.windows
        self._saved_at = now
