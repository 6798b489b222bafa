"""The pose stream on a real Unix socket: hello first, bounded queues, stuck clients never delay the producer."""

from __future__ import annotations

import asyncio
import io
import json
import logging
import math
import os
import socket
import stat
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from robotd.cli import main
from robotd.commands.pose import describe_pose, show
from robotd.daemon.poseclient import LineSplitter, decode
from robotd.daemon.posesock import PoseServer, encode, hello_message, pose_message, status_message


@pytest.fixture
def short_dir() -> Iterator[Path]:
    """A directory with a short path: a Unix socket path must fit in 108 bytes, pytest's tmp_path may not."""
    with tempfile.TemporaryDirectory(prefix="rd-", dir="/tmp") as name:
        yield Path(name)


def a_pose(t: float) -> dict[str, Any]:
    return pose_message(
        t=t,
        stamp=1_700_000_000.0 + t,
        pose=(1.0, 2.0, 0.5),
        twist=(0.1, 0.0, 0.2),
        covariance=[[0.01, 0.0, 0.0], [0.0, 0.04, 0.0], [0.0, 0.0, 0.0001]],
        fix_age_s=0.05,
        fix_state="accepted",
        odometry_state="ok",
    )


def test_pose_messages_carry_the_issue_fields_and_encode_as_one_json_line() -> None:
    line = encode(a_pose(3.0))
    assert line.endswith(b"\n")
    assert line.count(b"\n") == 1
    message = json.loads(line)
    assert message["frame_id"] == "map"
    assert message["child_frame_id"] == "base_link"
    assert message["covariance"] == [0.01, 0.0, 0.0, 0.0, 0.04, 0.0, 0.0, 0.0, 0.0001]
    assert (message["x"], message["y"], message["theta"]) == (1.0, 2.0, 0.5)
    with pytest.raises(ValueError, match="3x3"):
        pose_message(
            t=0, stamp=0, pose=(0, 0, 0), twist=(0, 0, 0), covariance=[1.0, 2.0], fix_age_s=None,
            fix_state="none", odometry_state="ok",
        )  # fmt: skip


def test_non_finite_numbers_become_null() -> None:
    status = status_message(t=1.0, stamp=2.0, drivers={"ips": {"lag": math.nan}}, filter_diagnostics={"nis": math.inf})
    message = json.loads(encode(status))
    assert message["drivers"]["ips"]["lag"] is None
    assert message["filter"]["nis"] is None


async def read_line(reader: asyncio.StreamReader) -> dict[str, Any]:
    line = await asyncio.wait_for(reader.readline(), 2.0)
    message: dict[str, Any] = json.loads(line)
    return message


async def test_clients_get_hello_then_what_is_published(short_dir: Path) -> None:
    path = short_dir / "run" / "pose.sock"
    server = PoseServer(path, 0o660, hello=hello_message(20.0, 1.0))
    await server.start()
    try:
        assert stat.S_IMODE(path.stat().st_mode) == 0o660
        reader, writer = await asyncio.open_unix_connection(str(path))
        try:
            assert (await read_line(reader))["type"] == "hello"
            while server.clients == 0:
                await asyncio.sleep(0.001)
            server.publish(a_pose(1.0))
            server.publish(a_pose(2.0))
            assert [(await read_line(reader))["t"] for _ in range(2)] == [1.0, 2.0]
        finally:
            writer.close()
            await writer.wait_closed()
    finally:
        await server.close()
    assert not path.exists()


async def test_a_client_that_never_reads_does_not_delay_the_producer(short_dir: Path) -> None:
    path = short_dir / "pose.sock"
    server = PoseServer(path, hello=hello_message(1000.0, 1.0), queue_size=8, stall_s=0.3)
    await server.start()
    stuck = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    stuck.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    stuck.connect(str(path))
    reader, writer = await asyncio.open_unix_connection(str(path))
    try:
        await read_line(reader)
        while server.clients < 2:
            await asyncio.sleep(0.001)
        received: list[float] = []

        async def keep_reading() -> None:
            while True:
                message = await read_line(reader)
                received.append(message["t"])

        reading = asyncio.create_task(keep_reading())
        slowest_publish, started = 0.0, time.monotonic()
        big = a_pose(0.0) | {"padding": "x" * 2000}  # fill the stuck client's socket quickly
        t = 0.0
        while time.monotonic() - started < 1.0:  # the producer: 1 kHz for one second
            t += 1.0
            before = time.perf_counter()
            server.publish(big | {"t": t})
            slowest_publish = max(slowest_publish, time.perf_counter() - before)
            await asyncio.sleep(0.001)
        await asyncio.sleep(0.05)
        reading.cancel()
        await asyncio.gather(reading, return_exceptions=True)
    finally:
        writer.close()
        await writer.wait_closed()
        stuck.close()
        await server.close()
    assert server.counters["stalled"] == 1, "the stuck client was not disconnected"
    assert server.counters["dropped_messages"] > 0
    assert slowest_publish < 0.02  # one publish is a few deque appends, never a wait on a socket
    assert received[-1] == t  # the reading client kept up to the last message
    assert received == sorted(received)


async def test_a_stale_socket_file_is_replaced_but_a_live_one_is_not(short_dir: Path) -> None:
    path = short_dir / "pose.sock"
    leftover = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    leftover.bind(str(path))
    leftover.close()  # a crashed daemon's socket: the file stays, nobody listens
    first = PoseServer(path)
    await first.start()
    try:
        with pytest.raises(FileExistsError, match="another process"):
            await PoseServer(path).start()
    finally:
        await first.close()
    path.write_text("not a socket")
    with pytest.raises(FileExistsError, match="not a socket"):
        await PoseServer(path).start()


async def test_closing_with_clients_connected_ends_their_streams_without_an_error(
    short_dir: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = short_dir / "pose.sock"
    server = PoseServer(path)
    await server.start()
    reader, writer = await asyncio.open_unix_connection(str(path))
    try:
        assert (await read_line(reader))["type"] == "hello"
        await server.close()
        assert await asyncio.wait_for(reader.read(), 2.0) == b""
        for _ in range(3):  # let asyncio run the connection's done-callbacks
            await asyncio.sleep(0)
    finally:
        writer.close()
        await writer.wait_closed()
    assert [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR] == []
    assert not path.exists()


async def test_clients_beyond_the_limit_get_one_error_line_then_the_close(short_dir: Path) -> None:
    path = short_dir / "pose.sock"
    server = PoseServer(path, max_clients=2)
    await server.start()
    connections = [await asyncio.open_unix_connection(str(path)) for _ in range(3)]
    try:
        for reader, _ in connections[:2]:
            assert (await read_line(reader))["type"] == "hello"
        refused = await asyncio.wait_for(connections[2][0].read(), 2.0)  # everything until the close
        assert refused.count(b"\n") == 1
        assert json.loads(refused) == {"type": "error", "error": "too many clients (max 2)"}
        assert server.counters["refused"] == 1
        server.publish({"type": "status", "n": 1})  # the clients within the limit are still served
        for reader, _ in connections[:2]:
            assert (await read_line(reader)) == {"type": "status", "n": 1}
    finally:
        for _, writer in connections:
            writer.close()
            await writer.wait_closed()
        await server.close()


async def test_robotd_pose_says_why_a_full_daemon_closed_it(
    short_dir: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = short_dir / "pose.sock"
    server = PoseServer(path, max_clients=1)
    await server.start()
    reader, writer = await asyncio.open_unix_connection(str(path))
    try:
        assert (await read_line(reader))["type"] == "hello"
        status = await asyncio.wait_for(asyncio.to_thread(main, ["pose", "--socket", str(path)]), 5.0)
    finally:
        writer.close()
        await writer.wait_closed()
        await server.close()
    assert status == 1
    err = capsys.readouterr().err
    assert err.splitlines() == ["robotd pose: the daemon closed the connection: too many clients (max 1)"]


def test_robotd_pose_prints_one_line_per_pose() -> None:
    lines = [line.decode() for line in (encode(hello_message(20.0, 1.0)), encode(a_pose(1.0)), encode(a_pose(2.0)))]
    out = io.StringIO()
    assert show([decode(line, 0.0) for line in lines], out, raw=False, count=2) == 0
    text = out.getvalue()
    assert text.startswith("connected: robotd-pose v1")
    assert text.count("\r") == 2
    assert "x   +1.000 m" in text
    assert describe_pose(a_pose(0.0)).count("deg") == 2


def test_robotd_pose_refuses_an_unknown_protocol() -> None:
    line = json.dumps({"type": "hello", "protocol": "other", "version": 9}) + "\n"
    assert show([decode(line, 0.0)], io.StringIO(), raw=False, count=None) == 1


def test_the_line_splitter_keeps_a_partial_line_and_marks_a_line_that_is_not_json() -> None:
    splitter = LineSplitter()
    whole = encode(a_pose(1.0))
    assert splitter.feed(whole[:10], 1.0) == []
    first, junk = splitter.feed(whole[10:] + b"not json\n{", 2.0)
    assert (first.kind, first.arrived, first.message) == ("pose", 2.0, json.loads(whole))
    assert (junk.message, junk.line) == (None, "not json\n")
    (last,) = splitter.feed(b'"type": "status"}\n', 3.0)
    assert last.kind == "status"


def test_robotd_pose_on_a_missing_socket_fails_cleanly(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["pose", "--socket", os.fspath(tmp_path / "absent.sock")]) == 1
    assert "cannot connect" in capsys.readouterr().err
