"""The learnt odometry calibration and noise kept across restarts, in the unit's StateDirectory (ekf.calibration_file).

A robot starts calibrated: the daemon loads the file at start (a missing file: the configuration's starting values;
a damaged one: one WARNING line, and the configuration's values), saves it when a calibration window changed it (at
most once a minute) and on its way out. Writes go to a temporary file renamed over the old one, so a crash never
leaves half a file. The uncertainty is saved too, and widened on load to at least a floor, so a robot changed while
the daemon was stopped is found out again. Kept with it: the fixes' judgement (their noise and the correlation of
their errors) and the learnt noise (the IPS noise in use, the process noise scales), so a restarted filter fuses its
first fixes for what they were found worth, not as independent ones at the configured noise.
"""

from __future__ import annotations

import json
import logging
import math
import os
from pathlib import Path
from typing import NamedTuple

from robotd.estimation.calibration import Calibration
from robotd.estimation.estimator import LearntNoise

log = logging.getLogger(__name__)
SAVE_EVERY_S = 60.0
FORMAT = "robotd-calibration"
MIN_SCALE_SIGMA = 0.02  # a saved calibration is trusted at most this much on load: the robot may have changed
MIN_LATENCY_SIGMA_S = 0.02
JUDGEMENT = ("fix_var", "fix_correlation", "fix_correlated_var")  # Calibration's judgement of the fixes, by file key


class Saved(NamedTuple):
    """What a run before learnt: the calibration (with its judgement of the fixes) and the noise."""

    calibration: Calibration
    noise: LearntNoise | None  # None in files written before robotd kept the noise


def read(path: str | Path) -> Saved:
    """The saved calibration and noise of a calibration file; OSError when it cannot be read, ValueError (saying
    which value) when it is not a calibration file robotd can use."""
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
        if not isinstance(data, dict) or data.get("format") != FORMAT:
            raise ValueError(f"not a {FORMAT} file")
        values = [float(data[key]) for key in ("kx", "ky", "kw", "latency_s", "time_error_s")]
        sigmas = [float(value) for value in data["sigmas"]]
        if len(sigmas) != 5 or not all(math.isfinite(v) for v in values + sigmas):
            raise ValueError("values must be 5 finite numbers and 5 sigmas")
        judgement = [float(data.get(key, 0.0)) for key in JUDGEMENT]
        if not all(math.isfinite(v) and v >= 0.0 for v in judgement) or judgement[1] >= 1.0:
            raise ValueError("the fixes' judgement must be finite, non-negative, and their correlation below 1")
        noise = None
        if "ips_sigma_m" in data:
            ips_sigma, scale = float(data["ips_sigma_m"]), float(data["process_noise_scale"])
            # a file written before the heading's own scale: the position's was the heading's too
            heading = float(data.get("heading_noise_scale", scale))
            if not all(math.isfinite(v) and v > 0.0 for v in (ips_sigma, scale, heading)):
                raise ValueError("ips_sigma_m, process_noise_scale and heading_noise_scale must be positive numbers")
            noise = LearntNoise(ips_sigma**2, scale, heading)
        windows = int(data.get("windows", 0))
    except (KeyError, TypeError, AttributeError) as error:
        raise ValueError(f"not a usable {FORMAT} file ({type(error).__name__}: {error})") from error
    floors = (MIN_SCALE_SIGMA, MIN_SCALE_SIGMA, MIN_SCALE_SIGMA, MIN_LATENCY_SIGMA_S, MIN_LATENCY_SIGMA_S)
    widened = tuple(max(s, f) for s, f in zip(sigmas, floors, strict=True))
    kx, ky, kw, latency, time_error = values
    sigmas_out = (widened[0], widened[1], widened[2], widened[3], widened[4])
    fix_var, correlation, correlated_var = judgement
    calibration = Calibration(
        kx, ky, kw, latency, time_error, sigmas_out, windows, correlated_var, correlation, fix_var
    )
    return Saved(calibration, noise)


def load(path: str) -> Saved | None:
    """The saved calibration and noise, or None (no path, no file, or a damaged file: said once at WARNING)."""
    if not path:
        return None
    try:
        return read(path)
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as error:
        log.warning("calibration file %s unusable (%s): starting from the configuration", path, error)
        return None


def save(path: str | Path, calibration: Calibration, noise: LearntNoise | None = None) -> None:
    """Write the calibration (and the noise, when given) atomically (OSError: the caller says so and runs on)."""
    c = calibration
    data: dict[str, object] = {
        "format": FORMAT,
        "kx": c.kx,
        "ky": c.ky,
        "kw": c.kw,
        "latency_s": c.latency_s,
        "time_error_s": c.time_error_s,
        "sigmas": list(c.sigmas),
        "windows": c.windows,
        # the fixes' judgement: without it a restarted filter would fuse correlated fixes as independent ones
        "fix_var": c.fix_var,
        "fix_correlation": c.fix_correlation,
        "fix_correlated_var": c.fix_correlated_var,
    }
    if noise is not None:
        data |= {
            "ips_sigma_m": math.sqrt(noise.ips_var),
            "process_noise_scale": noise.process_noise_scale,
            "heading_noise_scale": noise.heading_noise_scale,
        }
    target = Path(path)
    temporary = target.with_name(target.name + ".tmp")
    temporary.write_text(json.dumps(data) + "\n", encoding="utf-8")
    os.replace(temporary, target)


class CalibrationKeeper:
    """Saves the estimator's calibration when it changed, at most every SAVE_EVERY_S, and once more at the end."""

    def __init__(self, path: str) -> None:
        self.path = path
        self._saved_windows = -1
        self._saved_at = -math.inf
        self.failures = 0

    def maybe_save(
        self, calibration: Calibration, now: float, *, force: bool = False, noise: LearntNoise | None = None
    ) -> None:
        """Save if the calibration has new windows and it is time (or `force`), with the noise learnt by then; a
        failed write is one WARNING."""
        if not self.path or calibration.windows == self._saved_windows:
            return
        if not force and now - self._saved_at < SAVE_EVERY_S:
            return
        try:
            save(self.path, calibration, noise)
        except OSError as error:
            self.failures += 1
            log.warning("cannot save the calibration to %s: %s", self.path, error)
        else:
            self._saved_windows = calibration.windows
        self._saved_at = now
