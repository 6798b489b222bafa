"""`robotd demo` end to end: real processes, a shortened square, results written, nothing left running."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from paths import REPO
from process_support import processes_mentioning

from robotd.logs.sensorlog import read_log
from robotd.viz.mcaplog import read_mcap_log


def demo(out: Path, *extra: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "robotd", "demo", "--config", str(REPO / "config" / "sim.yaml"), "--out", str(out),
         *extra],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO,
    )  # fmt: skip


@pytest.mark.slow
def test_a_short_square_through_the_daemon_is_scored_and_leaves_no_process(tmp_path: Path) -> None:
    out = tmp_path / "demo"
    proc = demo(out, "--side", "0.6", "--speed", "0.3")
    output, _ = proc.communicate(timeout=120)
    assert proc.returncode == 0, output
    metrics = json.loads((out / "metrics.json").read_text())
    assert set(metrics) == {"odometry", "ips", "paper_ekf", "gated_ekf", "ekf"}
    # the live daemon's pose stream, scored against the virtual robot's truth
    assert metrics["ekf"]["samples"] > 100
    assert metrics["ekf"]["max_m"] < 0.15
    assert "robotd EKF (live daemon)" in (out / "results.md").read_text()
    for name in ("fig6_trajectories.png", "fig7_errors.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the run as MCAP too (issue 15): the same sensor log as the JSON Lines one, read back with the mcap reader
    assert read_mcap_log(out / "run.mcap").events == read_log(out / "run.jsonl").events
    assert processes_mentioning(str(out)) == []


@pytest.mark.slow
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_ctrl_c_or_sigterm_stops_every_process_the_demo_started(tmp_path: Path, signum: signal.Signals) -> None:
    out = tmp_path / "demo"
    proc = demo(out, "--side", "3")
    deadline = time.monotonic() + 30
    while not (out / "poses.jsonl").exists() or (out / "poses.jsonl").stat().st_size == 0:
        assert proc.poll() is None, proc.communicate()[0]
        assert time.monotonic() < deadline
        time.sleep(0.1)
    children = set(processes_mentioning(str(out))) - {proc.pid}
    assert len(children) == 2  # the virtual robot and the daemon
    proc.send_signal(signum)
    output, _ = proc.communicate(timeout=30)
    assert proc.returncode == 128 + signum, output
    assert "every process it started has been stopped" in output
    assert processes_mentioning(str(out)) == []
