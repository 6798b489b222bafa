"""Shared helpers of the Marvelmind tests: the real captures and the ways of cutting a stream into reads."""

from __future__ import annotations

import random
from collections.abc import Iterator

import pytest
from paths import MARVELMIND_FIXTURES as FIXTURES

from drivers.marvelmind.events import Counters, Event
from drivers.marvelmind.protocol import MarvelmindParser


def capture(name: str) -> bytes:
    """A real capture from the shared fixtures (skips the test when the shared folder is absent)."""
    path = FIXTURES / name
    if not path.exists():
        pytest.skip(f"shared fixture {path} is not present")
    return path.read_bytes()


def whole(data: bytes) -> Iterator[bytes]:
    yield data


def byte_by_byte(data: bytes) -> Iterator[bytes]:
    for index in range(len(data)):
        yield data[index : index + 1]


def random_splits(data: bytes, seed: int) -> Iterator[bytes]:
    """Reads of 1 to 40 bytes at seeded random split points."""
    rng = random.Random(seed)
    index = 0
    while index < len(data):
        size = rng.randint(1, 40)
        yield data[index : index + size]
        index += size


def chunkings(data: bytes) -> dict[str, list[bytes]]:
    """The stream whole, byte by byte and at three sets of random split points."""
    cuts = {"whole": list(whole(data)), "byte_by_byte": list(byte_by_byte(data))}
    cuts |= {f"random_{seed}": list(random_splits(data, seed)) for seed in (1, 2, 3)}
    return cuts


def parse_reads(reads: list[bytes], parser: MarvelmindParser | None = None) -> tuple[list[Event], Counters]:
    """Feed the reads (all at arrival 1.0), then end the stream; the events and counters."""
    parser = parser if parser is not None else MarvelmindParser()
    events: list[Event] = []
    for read in reads:
        events += parser.feed(read, arrival=1.0)
    parser.finish()
    return events, parser.counters
