"""The daemon's running cost under `robotd sim`: wake-ups, system calls and CPU, at rest and driving at 0.3 m/s.

Theory of operation. The figures are counted by the kernel, not timed, so they hardly vary with the machine's load:
- wake-ups: the daemon's voluntary context switches, summed over its threads (/proc/PID/task/*/status): each one
  is a sleep the process asked for (epoll_wait, a blocking receive) that a timer or an arrival ended;
- system calls: every system call of every thread, counted in the kernel by `perf stat -e raw_syscalls:sys_enter`
  (a tracepoint counter: the process is not stopped, unlike under strace); where perf cannot run, the read- and
  write-like calls of /proc/PID/io (`syscr` + `syscw`, which leave out socket sends and receives, epoll_wait and
  the rest), and the line says which;
- CPU: user plus system time from /proc/PID/stat, as a share of one core.
At rest: nobody commands the robot and no pose client is connected, as under `robotd sim` alone. Driving: a teleop
client at 20 Hz, 0.3 m/s forward and back. Baselines: the targets of issue 18 (wake-ups <= 30/s at rest and
<= 150/s driving, CPU <= 1 % at rest and <= 5 % driving). Beside each CPU figure, the floor: a process of its own
with an asyncio loop that does nothing but wake as often as the daemon did, measured the same way. A wake-up's cost
is the machine's (a virtual machine's timer and scheduler exits cost more than a Pi's), and the CPU figure less the
floor is what robotd's own work costs.
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from robotd.kinematics import Twist
from robotd.tools.teleop_client import UdpLink

NAME = "budget"
DRIVE_SPEED_MPS = 0.3
TARGET_WAKEUPS_PER_S = {"rest": 30.0, "driving": 150.0}
TARGET_CPU_SHARE = {"rest": 0.01, "driving": 0.05}


@dataclass(frozen=True, slots=True)
class ProcessCounts:
    """What the kernel has counted for a process so far."""

    t: float
    voluntary_switches: int
    main_thread_switches: int
    syscalls: int
    cpu_s: float


@dataclass(frozen=True, slots=True)
class Rates:
    """Per-second rates between two `ProcessCounts`."""

    wakeups_per_s: float
    main_thread_wakeups_per_s: float
    syscalls_per_s: float
    syscalls_counted_by: str
    cpu_share: float
    floor_cpu_share: float | None = None  # of a bare asyncio loop waking as often (wakeup_floor), when measured


def _voluntary(status: Path) -> int:
    try:
        text = status.read_text(encoding="ascii")
    except (FileNotFoundError, ProcessLookupError):  # the thread ended meanwhile
        return 0
    for line in text.splitlines():
        if line.startswith("voluntary_ctxt_switches:"):
            return int(line.split()[1])
    return 0


def voluntary_switches(pid: int) -> tuple[int, int]:
    """Voluntary context switches of every thread of a process (threads that ended are not counted), and of its
    main thread (the event loop's)."""
    total = sum(_voluntary(status) for status in Path(f"/proc/{pid}/task").glob("*/status"))
    return total, _voluntary(Path(f"/proc/{pid}/task/{pid}/status"))


def io_syscalls(pid: int) -> int:
    """Read- and write-like system calls of a process so far (/proc/PID/io: syscr + syscw)."""
    values = dict(line.split(": ") for line in Path(f"/proc/{pid}/io").read_text(encoding="ascii").splitlines())
    return int(values["syscr"]) + int(values["syscw"])


def counts(pid: int) -> ProcessCounts:
    """The process's counts now."""
    from robotd.bench.daemon import cpu_seconds  # noqa: PLC0415 - daemon.py imports this module

    total, main = voluntary_switches(pid)
    return ProcessCounts(time.monotonic(), total, main, io_syscalls(pid), cpu_seconds(pid))


class SyscallCounter:
    """Every system call of a process over an interval, counted by `perf stat` (None when perf cannot)."""

    def __init__(self, pid: int, seconds: float) -> None:
        self._proc: subprocess.Popen[str] | None = None
        perf = shutil.which("perf")
        if perf is None:
            return
        command = [perf, "stat", "-x,", "-e", "raw_syscalls:sys_enter", "-p", str(pid), "--", "sleep", f"{seconds}"]
        self._proc = subprocess.Popen(  # noqa: S603 - a fixed command line
            command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
        )

    def result(self) -> int | None:
        """The count, once the interval is over; None when perf could not count."""
        if self._proc is None:
            return None
        _, errors = self._proc.communicate()
        for line in errors.splitlines():
            fields = line.split(",")
            if len(fields) > 2 and fields[2] == "raw_syscalls:sys_enter" and fields[0].isdigit():
                return int(fields[0])
        return None


def rates(before: ProcessCounts, after: ProcessCounts, perf_count: int | None) -> Rates:
    """Rates over the interval between two counts (system calls from perf's count when there is one)."""
    seconds = after.t - before.t
    if perf_count is not None:
        calls, by = perf_count / seconds, "perf raw_syscalls:sys_enter"
    else:
        calls, by = (after.syscalls - before.syscalls) / seconds, "/proc/PID/io syscr+syscw: reads and writes only"
    return Rates(
        (after.voluntary_switches - before.voluntary_switches) / seconds,
        (after.main_thread_switches - before.main_thread_switches) / seconds,
        calls,
        by,
        (after.cpu_s - before.cpu_s) / seconds,
    )


# the floor's process: an asyncio loop woken by a timer `rate` times a second for `seconds`, nothing else; it prints
# its own CPU time (user + system, the clock ticks /proc/PID/stat counts) over that interval
_FLOOR_PROGRAM = """
import asyncio, os, sys
rate, seconds = float(sys.argv[1]), float(sys.argv[2])
async def main():
    loop = asyncio.get_running_loop()
    start, before = loop.time(), os.times()
    n = 0
    while loop.time() - start < seconds:
        n += 1
        await asyncio.sleep(max(start + n / rate - loop.time(), 0.0))
    after = os.times()
    spent = (after.user + after.system) - (before.user + before.system)  # whole clock ticks, as float seconds
    print(max(spent, 0.0) / (loop.time() - start))
asyncio.run(main())
"""


def wakeup_floor(wakeups_per_s: float, seconds: float) -> float | None:
    """The CPU share of one core that a bare asyncio loop waking `wakeups_per_s` times a second costs on this
    machine, in a Python process of its own (the daemon's interpreter); None when it could not be measured."""
    if wakeups_per_s <= 0.0:
        return 0.0
    try:
        done = subprocess.run(  # noqa: S603 - this interpreter and a fixed program
            [sys.executable, "-c", _FLOOR_PROGRAM, f"{wakeups_per_s}", f"{seconds}"],
            capture_output=True,
            text=True,
            timeout=seconds + 30.0,
            check=True,
        )
        return float(done.stdout.strip())
    except (OSError, subprocess.SubprocessError, ValueError):
        return None


def phase(pid: int, seconds: float, activity: Callable[[float], None]) -> Rates:
    """The process's rates while `activity(seconds)` runs."""
    before = counts(pid)
    counter = SyscallCounter(pid, seconds)
    activity(seconds)
    after = counts(pid)
    return rates(before, after, counter.result())


Drive = Callable[[UdpLink, float, float], None]
"""Teleop at a speed (m/s) for a duration (s)."""


def measure(pid: int, link: UdpLink, seconds: float, drive: Drive) -> dict[str, Rates]:
    """Rates at rest (nobody commanding), then driving at DRIVE_SPEED_MPS, each over `seconds`."""
    time.sleep(min(2.0, seconds / 2))  # whatever came before has settled (the deadman's timeout, a braking robot)
    rest = phase(pid, seconds, time.sleep)
    drive(link, DRIVE_SPEED_MPS, 1.0)  # up to speed first
    driving = phase(pid, seconds, lambda s: drive(link, DRIVE_SPEED_MPS, s))
    link.send(Twist(0.0, 0.0, 0.0))
    return {
        name: dataclasses.replace(r, floor_cpu_share=wakeup_floor(r.wakeups_per_s, seconds))
        for name, r in (("rest", rest), ("driving", driving))
    }


def report(measured: dict[str, Rates]) -> dict[str, float]:
    """Print one line per phase against the targets; the figures by name."""
    figures: dict[str, float] = {}
    for name, r in measured.items():
        wake_target, cpu_target = TARGET_WAKEUPS_PER_S[name], TARGET_CPU_SHARE[name]
        what = "at rest" if name == "rest" else f"driving at {DRIVE_SPEED_MPS} m/s"
        print(
            f"daemon {what}: {r.wakeups_per_s:.0f} wake-ups/s ({r.main_thread_wakeups_per_s:.0f} of the event loop's"
            f" thread; target <= {wake_target:.0f}: ratio {r.wakeups_per_s / wake_target:.2f}), "
            f"{r.syscalls_per_s:.0f} system calls/s ({r.syscalls_counted_by}), CPU {r.cpu_share * 100:.1f}% of one "
            f"core (target <= {cpu_target * 100:.0f}%: ratio {r.cpu_share / cpu_target:.2f})" + _floor_note(r)
        )
        if r.floor_cpu_share is not None:
            figures[f"{name}_floor_cpu_share"] = r.floor_cpu_share
        figures |= {
            f"{name}_wakeups_per_s": r.wakeups_per_s,
            f"{name}_loop_thread_wakeups_per_s": r.main_thread_wakeups_per_s,
            f"{name}_syscalls_per_s": r.syscalls_per_s,
            f"{name}_cpu_share": r.cpu_share,
        }
    return figures


def _floor_note(r: Rates) -> str:
    if r.floor_cpu_share is None:
        return "; the wake-up floor could not be measured"
    return (
        f"; floor {r.floor_cpu_share * 100:.1f}% (a bare asyncio loop waking {r.wakeups_per_s:.0f} times/s here), "
        f"robotd's own work {max(r.cpu_share - r.floor_cpu_share, 0.0) * 100:.1f}%"
    )


def run(quick: bool, runs: int = 1) -> dict[str, float]:
    """`runs` fresh daemons on the virtual robot, each measured at rest and driving; the median of each figure."""
    from robotd.bench.daemon import BENCH_OVERRIDES, bench_config, drive_back_and_forth, running  # noqa: PLC0415

    seconds = 3.0 if quick else 10.0
    collected: dict[str, list[float]] = {}
    for _ in range(runs):
        with tempfile.TemporaryDirectory(prefix="robotd-budget-") as tmp:
            out = Path(tmp)
            with running(bench_config(out, BENCH_OVERRIDES), out) as (config, _vhw, daemon):
                link = UdpLink("127.0.0.1", config.teleop.port, None)
                try:
                    if not link.sync(5.0):
                        raise RuntimeError("the daemon did not answer the teleop hello")
                    figures = report(measure(daemon.pid, link, seconds, drive_back_and_forth))
                finally:
                    link.sock.close()
        for name, value in figures.items():
            collected.setdefault(name, []).append(value)
    medians = {name: statistics.median(values) for name, values in collected.items()}
    if runs > 1:
        print(f"medians of {runs} runs:")
        report_medians = {
            name: Rates(
                medians[f"{name}_wakeups_per_s"],
                medians[f"{name}_loop_thread_wakeups_per_s"],
                medians[f"{name}_syscalls_per_s"],
                "median",
                medians[f"{name}_cpu_share"],
                medians.get(f"{name}_floor_cpu_share"),
            )
            for name in ("rest", "driving")
        }
        report(report_medians)
    return medians


def main() -> None:
    """`python -m robotd.bench.budget [--quick] [--runs N]`."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--runs", type=int, default=1)
    args = parser.parse_args()
    run(args.quick, args.runs)


if __name__ == "__main__":
    main()
