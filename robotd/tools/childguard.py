"""`python -m robotd.tools.childguard PARENT_PID ARGS...`: run `robotd ARGS` as a child that dies with its parent.

Theory of operation. `robotd sim` and `robotd demo` stop their children in order on every signal they can catch, but
nothing runs in a process that is SIGKILLed (or dies of a crash in C). Linux's prctl(PR_SET_PDEATHSIG) asks the
kernel itself to send a signal to a process when the thread that started it ends, however it ends: the child sets
SIGTERM on itself here, before anything else, so it then stops as on `kill` (the daemon zeroes the motors, the
virtual robot closes its pseudo-terminal) instead of running on as an orphan. It must be the child that asks:
subprocess has no such option, and a `preexec_fn` is unsafe once the parent runs threads (the pose recorder). The
parent may have died before the call; the parent's pid given on the command line tells (the orphan's parent is then
someone else), and the child does not start. prctl is called through ctypes: a single libc call, no dependency. On a
system without prctl the guard is skipped and the parent's signal handlers are the only protection.
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys
from collections.abc import Sequence

PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def die_with_parent(signum: int = signal.SIGTERM) -> bool:
    """Ask the kernel for `signum` when our parent ends; False where prctl does not exist (not Linux)."""
    if not sys.platform.startswith("linux"):
        return False
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_SET_PDEATHSIG, signum, 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")
    return True


def main(argv: Sequence[str]) -> int:
    """Guard this process, then run `robotd ARGV[1:]` if the parent ARGV[0] is still alive."""
    parent = int(argv[0])
    die_with_parent()
    if os.getppid() != parent:  # the parent ended before the guard was set: nobody is left to stop us
        print(f"robotd: parent process {parent} has already exited; not starting {' '.join(argv[1:])}", file=sys.stderr)
        return os.EX_UNAVAILABLE
    from robotd.cli import main as robotd_main  # noqa: PLC0415 - only after the guard is in place

    return robotd_main(list(argv[1:]))


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
