"""Flooding the teleop port: hostile datagrams, a paced sender that loses none, and a sender as fast as one process.

`hostile_datagrams` builds datagrams every check must refuse (random bytes, and valid ones broken one way each);
`flood` sends them paced on the receiver's queue (/proc/net/udp) so that the kernel drops none and each must be
counted; `blast` sends as fast as one process can, from a child process so that the measuring process keeps its
own core time.
"""

from __future__ import annotations

import contextlib
import math
import random
import socket
import struct
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from robotd.daemon.teleop import DATAGRAM_SIZE, TAG_SIZE, TeleopSender
from robotd.kinematics import Twist
from robotd.tools.teleop_client import UdpLink


def hostile_datagrams(rng: random.Random, count: int, now: Callable[[], float] = time.time) -> Iterator[bytes]:
    """`count` datagrams the daemon must reject: random bytes, and valid ones broken in ways no check may miss."""
    sender = TeleopSender(None)
    for _ in range(count):
        valid = bytearray(sender.command(Twist(rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(-2, 2)), now()))
        kind = rng.randrange(8)
        if kind == 0:  # noise of any length, never starting like a datagram
            data = bytearray(rng.randbytes(rng.randrange(0, 2 * DATAGRAM_SIZE)))
            if data[:3] == b"RBT":
                data[0] ^= 0xFF
        elif kind == 1:  # truncated or extended
            cut = rng.randrange(0, DATAGRAM_SIZE)
            data = valid[:cut] if rng.random() < 0.5 else valid + rng.randbytes(rng.randrange(1, 64))
        elif kind == 2:  # a zero session, a reserved bit, or a type a daemon does not take
            field = rng.randrange(3)
            if field == 0:
                valid[8:12] = b"\0\0\0\0"
            elif field == 1:
                valid[5 + rng.randrange(3)] |= 1 << rng.randrange(8)
            else:
                valid[4] = rng.choice([0, 4, 255])
            data = valid
        elif kind == 3:  # not a number where a velocity or the time belongs
            offset = rng.choice([32, 40, 48, 56])
            valid[offset : offset + 8] = struct.pack(">d", rng.choice([math.nan, math.inf, -math.inf]))
            data = valid
        elif kind == 4:  # a sender clock far from ours
            valid[32:40] = struct.pack(">d", now() + rng.choice([-1, 1]) * rng.uniform(60.0, 1e6))
            data = valid
        elif kind == 5:  # another wire version
            valid[3] = rng.choice([0, 1, 255])
            data = valid
        else:  # random bit flips anywhere, one of them in the tag: a keyless daemon takes only an all-zero tag
            for _ in range(rng.randrange(0, 6)):
                valid[rng.randrange(DATAGRAM_SIZE)] ^= 1 << rng.randrange(8)
            valid[DATAGRAM_SIZE - TAG_SIZE + rng.randrange(TAG_SIZE)] |= 1 << rng.randrange(8)
            data = valid
        yield bytes(data)


def udp_queue(port: int) -> tuple[int, int]:
    """(bytes waiting, datagrams dropped) of the IPv4 UDP socket bound to `port`, from /proc/net/udp."""
    for line in Path("/proc/net/udp").read_text(encoding="ascii").splitlines()[1:]:
        fields = line.split()
        if int(fields[1].split(":")[1], 16) == port and fields[2] == "00000000:0000":
            return int(fields[4].split(":")[1], 16), int(fields[-1])
    raise LookupError(f"no UDP socket bound to port {port}")


def flood(port: int, datagrams: Iterator[bytes], max_queued_bytes: int = 64_000, burst: int = 32) -> int:
    """Send every datagram to 127.0.0.1:`port`, waiting whenever the receiver's queue is long; returns the count."""
    sent = 0
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.connect(("127.0.0.1", port))
        for data in datagrams:
            sock.send(data)
            sent += 1
            if sent % burst == 0:
                while udp_queue(port)[0] > max_queued_bytes:
                    time.sleep(0.0005)
    return sent


def blast(port: int, duration_s: float, sync: bool, seed: int = 7) -> tuple[int, float, float]:
    """Send to 127.0.0.1:`port` as fast as one process can for `duration_s`: 7 in 8 hostile, 1 in 8 a fresh stop.

    With `sync` the stops carry the daemon's instance (asked for first), so they pass every check but the rate
    limit: they show that valid datagrams from a flooding source are held to its rate and cannot run the controller
    at theirs. Returns the datagrams sent and the monotonic times of the first and the last.
    """
    link = UdpLink("127.0.0.1", port, None)
    try:
        if sync and not link.sync(5.0):
            raise RuntimeError("the daemon did not answer the flooder's hello")
        hostile = list(hostile_datagrams(random.Random(seed), 4096))
        send, stop, sent = link.sock.send, link.sender.stop, 0
        started = time.monotonic()
        deadline = started + duration_s
        while time.monotonic() < deadline:
            for index, datagram in enumerate(hostile):
                with contextlib.suppress(BlockingIOError, ConnectionRefusedError):
                    send(stop(time.time()) if index % 8 == 0 else datagram)
            sent += len(hostile)
    finally:
        link.sock.close()
    return sent, started, time.monotonic()


def main() -> None:
    """Entry point of the flooding child process: port, duration and sync (0 or 1) as arguments, `blast`'s out."""
    print(*blast(int(sys.argv[1]), float(sys.argv[2]), sys.argv[3] == "1"))


def blast_from_child(port: int, duration_s: float, *, sync: bool) -> tuple[int, float, float]:
    """`blast` from a child process (the system's monotonic clock is the same in both)."""
    code = "from robotd.bench.flood import main; main()"
    result = subprocess.run(  # noqa: S603 - our own interpreter running our own module
        [sys.executable, "-c", code, str(port), str(duration_s), "1" if sync else "0"],
        capture_output=True,
        text=True,
        check=True,
    )
    sent, started, ended = result.stdout.split()[-3:]
    return int(sent), float(started), float(ended)
