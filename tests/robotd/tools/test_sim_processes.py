"""`robotd sim` as a user runs it: no process left behind on any stop signal or SIGKILL, and a clean start after a
killed run."""

from __future__ import annotations

import os
import signal
import socket
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest
from process_support import processes_mentioning, start_sim, wait_for_output, wait_until_gone

READY = "Ctrl-C stops both."
pytestmark = pytest.mark.slow


@pytest.fixture
def out() -> Iterator[Path]:
    """The sim's folder, on a short path (its pose socket's path must fit in 108 bytes)."""
    with tempfile.TemporaryDirectory(prefix="rs-", dir="/tmp") as name:
        yield Path(name) / "sim"
        for pid in processes_mentioning(name):  # a failed test must not leave its processes to the next ones
            os.kill(pid, signal.SIGKILL)


def survivors(pids: list[int], out: Path) -> str:
    """What a failure needs to say: each survivor's command line and state, and the tails of the logs."""
    lines = []
    for pid in pids:
        try:
            cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            state = Path(f"/proc/{pid}/status").read_text().splitlines()[:3]
        except OSError:
            continue
        lines.append(f"{pid}: {cmdline} {state}")
    lines.extend(
        f"--- {log.name}:\n" + "\n".join(log.read_text(errors="replace").splitlines()[-15:])
        for log in sorted(out.glob("*.log"))
    )
    return "\n".join(lines)


@pytest.mark.parametrize(
    ("signum", "to_the_group"),
    [
        (signal.SIGTERM, False),  # kill PID
        (signal.SIGHUP, True),  # the terminal hangs up: its foreground process group gets SIGHUP
        (signal.SIGINT, True),  # Ctrl-C: the same, with SIGINT
    ],
    ids=["kill", "terminal-hang-up", "ctrl-c"],
)
def test_a_stop_signal_stops_the_daemon_then_the_virtual_robot_and_leaves_no_process(
    out: Path, signum: signal.Signals, to_the_group: bool
) -> None:
    proc, output = start_sim(out)
    wait_for_output(proc, output, READY)
    assert len(set(processes_mentioning(str(out))) - {proc.pid}) == 2  # the virtual robot and the daemon
    if to_the_group:
        os.killpg(proc.pid, signum)
    else:
        proc.send_signal(signum)
    assert proc.wait(60) == 0, output.read_text()
    text = output.read_text()
    # the daemon first (it zeroes the motors while the virtual pigpiod still listens), both stopped by their SIGTERM
    assert f"robotd sim: {signum.name}: stopped robotd run (exit 0), robotd vhw (exit 0)" in text
    assert "Traceback" not in text
    assert "Traceback" not in (out / "daemon.log").read_text()  # (a connected pose client included)
    assert processes_mentioning(str(out)) == []


def test_the_children_die_with_a_sigkilled_sim(out: Path) -> None:
    proc, output = start_sim(out)
    wait_for_output(proc, output, READY)
    children = set(processes_mentioning(str(out))) - {proc.pid}
    assert len(children) == 2
    proc.kill()
    proc.wait(10)
    left = wait_until_gone(str(out), timeout_s=30.0)
    assert left == [], survivors(left, out)
    # each child was told by the kernel and stopped as on SIGTERM: the daemon zeroed its motors on the way out
    assert "Traceback" not in (out / "daemon.log").read_text()


def test_a_killed_runs_stale_socket_and_device_link_do_not_stop_the_next_start(out: Path) -> None:
    out.mkdir()
    leftover = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    leftover.bind(str(out / "pose.sock"))
    leftover.close()  # what a killed daemon leaves: the file, nobody listening
    (out / "marvelmind").symlink_to("/dev/pts/999999")  # and a killed virtual robot: a link to a gone terminal
    proc, output = start_sim(out)
    wait_for_output(proc, output, READY)
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(60) == 0, output.read_text()
    assert "Traceback" not in output.read_text()
    assert (out / "poses.jsonl").stat().st_size > 0  # the pose recorder reached the new daemon
    assert processes_mentioning(str(out)) == []
