"""`robotd ips decode` on the real captures and `robotd ips listen` on a real pseudo-terminal."""

from __future__ import annotations

import io
import json
import os
import pty
import select
import signal
import subprocess
import sys
import time
import tty
from pathlib import Path

import pytest
from marvelmind_support import capture
from paths import MARVELMIND_FIXTURES as FIXTURES
from paths import REPO as REPO_ROOT

from drivers.marvelmind.frames import encode_position_mm
from robotd.cli import main


def test_decode_prints_one_json_object_per_event_and_counters_on_stderr(capsys: pytest.CaptureFixture[str]) -> None:
    capture("corrupted_capture_2016.bin")  # skips when the shared fixtures are absent
    assert main(["ips", "decode", str(FIXTURES / "corrupted_capture_2016.bin")]) == 0
    out, err = capsys.readouterr()
    events = [json.loads(line) for line in out.splitlines()]
    assert len(events) == 141
    assert [e["type"] for e in events].count("position") == 140
    assert (events[0]["x"], events[0]["y"], events[0]["z"], events[0]["timestamp"]) == (0.07, -0.16, 1.56, 5542)
    counters = json.loads(err)["counters"]
    assert counters["junk_bytes"] == 49
    assert counters["frames_by_code"] == {"0x0001": 140, "0x0002": 1}


def test_decode_reads_stdin(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setattr(sys, "stdin", io.TextIOWrapper(io.BytesIO(capture("clean_capture_2016.bin"))))
    assert main(["ips", "decode", "-", "--address", "0"]) == 0
    out, _ = capsys.readouterr()
    assert len(out.splitlines()) == 143


def test_decode_of_a_missing_file_is_a_clear_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["ips", "decode", str(tmp_path / "absent.bin")]) == 66
    assert "cannot read" in capsys.readouterr().err


def test_listen_streams_a_live_device_until_ctrl_c(tmp_path: Path) -> None:
    master, slave = pty.openpty()
    tty.setraw(slave)
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
    process = subprocess.Popen(
        [sys.executable, "-m", "robotd", "ips", "listen", os.ttyname(slave)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        cwd=REPO_ROOT,
        env=env,
    )
    try:
        assert process.stdout is not None
        deadline, stamp, line = time.monotonic() + 10.0, 0, b""
        while not line:
            assert time.monotonic() < deadline, "no event from robotd ips listen"
            stamp += 1
            os.write(master, encode_position_mm(stamp, 1.5, -0.5, 0.0, address=3))
            if select.select([process.stdout], [], [], 0.05)[0]:
                line = process.stdout.readline()
        event = json.loads(line)
        assert (event["type"], event["x"], event["y"], event["address"]) == ("position", 1.5, -0.5, 3)
        process.send_signal(signal.SIGINT)
        _, err = process.communicate(timeout=5.0)
        assert process.returncode == 0
        assert '"counters"' in err.decode()
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
        os.close(slave)
        os.close(master)
