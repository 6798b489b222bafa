"""`robotd replay`'s estimates.jsonl: one estimate of robotd's filter a line, written and read with msgspec.

A line: `{"t":0.05,"x":-0.35,"y":1.2,"theta":0.01,"cov":[...]}`: the time and pose rounded to six decimals (as the
sensor log's numbers), the 3x3 covariance row-major in full precision.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import BinaryIO

import msgspec

from robotd.estimation import ekf
from robotd.logs.events import DECIMALS


class Estimate(msgspec.Struct, frozen=True):
    """One estimate: time (s), pose (m, m, rad), covariance row-major."""

    t: float
    x: float
    y: float
    theta: float
    cov: tuple[float, float, float, float, float, float, float, float, float]


def write_estimates(stream: BinaryIO, estimates: Iterable[tuple[float, float, float, float, ekf.Cov]]) -> None:
    """Write (t, x, y, theta, P's upper triangle) tuples as estimates.jsonl lines."""
    encode = msgspec.json.Encoder().encode_into
    buffer = bytearray()
    for t, x, y, theta, p in estimates:
        line = Estimate(
            round(t, DECIMALS), round(x, DECIMALS), round(y, DECIMALS), round(theta, DECIMALS), ekf.cov_full(p)
        )
        encode(line, buffer, -1)
        buffer += b"\n"
        if len(buffer) > 1 << 16:
            stream.write(buffer)
            buffer.clear()
    stream.write(buffer)


def read_estimates(path: str | Path) -> list[Estimate]:
    """The estimates of an estimates.jsonl file (msgspec.DecodeError on a malformed line: robotd wrote it)."""
    decode = msgspec.json.Decoder(Estimate).decode
    return [decode(line) for line in Path(path).read_bytes().splitlines() if line]


__all__ = ["Estimate", "read_estimates", "write_estimates"]
