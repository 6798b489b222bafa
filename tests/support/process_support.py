"""Real `robotd sim` / `robotd demo` processes and other Python children for the tests, and the processes still
running from a folder."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

from paths import REPO

SIM_CONFIG = REPO / "config" / "sim.yaml"


def processes_mentioning(text: str) -> list[int]:
    """PIDs whose command line contains `text` (our own children have the demo's folder in theirs)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            state = (entry / "stat").read_text().rsplit(")", 1)[1].split()[0]
        except (OSError, IndexError):
            continue
        if text in cmdline and state != "Z":  # a zombie is dead (its parent has yet to reap it)
            found.append(int(entry.name))
    return found


def wait_until_gone(text: str, timeout_s: float) -> list[int]:
    """Wait (up to a generous bound) until no process mentions `text`; returns those left."""
    deadline = time.monotonic() + timeout_s
    while (left := processes_mentioning(text)) and time.monotonic() < deadline:
        time.sleep(0.1)
    return left


def python_child(args: list[str], *, stderr: int | None = None) -> subprocess.Popen[str]:
    """`python ARGS` from the repository with its packages importable, its output piped (text), as a shell runs it."""
    return subprocess.Popen(
        [sys.executable, *args],
        cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        stdout=subprocess.PIPE,
        stderr=stderr,
        text=True,
    )


def start_sim(out: Path) -> tuple[subprocess.Popen[str], Path]:
    """`robotd sim --out OUT` with its output in a file beside OUT."""
    output = out.with_name(out.name + ".out")
    with output.open("w", encoding="utf-8") as stream:
        proc = subprocess.Popen(
            [sys.executable, "-m", "robotd", "sim", "--config", str(SIM_CONFIG), "--out", str(out)],
            stdout=stream, stderr=subprocess.STDOUT, text=True, cwd=REPO,
            start_new_session=True,  # its own process group, as a shell gives a foreground job
        )  # fmt: skip
    return proc, output


def wait_for_output(proc: subprocess.Popen[str], output: Path, text: str, timeout_s: float = 60.0) -> None:
    """Wait until the process has printed `text` (failing if it exits first)."""
    deadline = time.monotonic() + timeout_s
    while text not in output.read_text(encoding="utf-8"):
        assert proc.poll() is None, output.read_text(encoding="utf-8")
        assert time.monotonic() < deadline, output.read_text(encoding="utf-8")
        time.sleep(0.1)
