"""`robotd replay`'s estimates.jsonl: one estimate of robotd's filter a line, written and read with msgspec.

A line: `{"t":0.05,"x":-0.35,"y":1.2,"theta":0.01,"cov":[...]}`: the time and pose rounded to six decimals (as the
sensor log's numbers), the 3x3 covariance row-major in full precision.
"""

from __future__ import annotations

from pathlib import Path
from typing import BinaryIO

import msgspec
import numpy as np
import numpy.typing as npt

from robotd.estimation import ekf
from robotd.logs.events import DECIMALS


class Estimate(msgspec.Struct, frozen=True):
    """One estimate: time (s), pose (m, m, rad), covariance row-major."""

    t: float
    x: float
    y: float
    theta: float
    cov: tuple[float, float, float, float, float, float, float, float, float]


FloatArray = npt.NDArray[np.float64]
_ENCODER = msgspec.json.Encoder()

_CHUNK = 8192  # estimates encoded at a time: an hour's file is about 90 MB


def write_estimates(stream: BinaryIO, poses: FloatArray, cov: FloatArray) -> None:
    """Write estimates.jsonl lines: `poses` one row (t, x, y, theta) per estimate, `cov` one row (P's upper triangle)
    per estimate.

    Rounded in numpy and encoded a chunk at a time: an hour's replay writes some 360 000 lines, and a round() per
    number and an encoder call per line took twice as long.
    """
    for start in range(0, len(poses), _CHUNK):
        rounded = np.round(poses[start : start + _CHUNK], DECIMALS)
        columns = (rounded[:, k].tolist() for k in range(4))
        rows = cov[start : start + _CHUNK].tolist()
        lines = [Estimate(t, x, y, theta, ekf.cov_full(p)) for t, x, y, theta, p in zip(*columns, rows, strict=True)]
        stream.write(_ENCODER.encode_lines(lines))


def read_estimates(path: str | Path) -> list[Estimate]:
    """The estimates of an estimates.jsonl file (msgspec.DecodeError on a malformed line: robotd wrote it)."""
    decode = msgspec.json.Decoder(Estimate).decode
    return [decode(line) for line in Path(path).read_bytes().splitlines() if line]


__all__ = ["Estimate", "read_estimates", "write_estimates"]
