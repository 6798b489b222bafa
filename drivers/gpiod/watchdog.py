"""A tiny process that stops the RP1's PWM channels when the process that started it dies, however it dies.

Theory of operation: the motors' owner starts `python -m drivers.gpiod.watchdog CHIP CHANNEL...` with a pipe on its
standard input and keeps the write end. The watchdog reads until end of file, which comes when the owner closes the
pipe or when the kernel closes it for an owner that died (SIGKILL, a crash, the OOM killer), then writes duty 0 and
enable 0 on its channels (drivers.gpiod.pwm.stop_pwm_channels) and exits. It runs in its own session and ignores
SIGINT, SIGTERM and SIGHUP: a Ctrl-C or systemd's stop reach the owner, which zeroes its motors itself; the pipe
then closes and the watchdog follows.

Not a substitute for systemd's ExecStopPost (`robotd stop-motors`): a SIGKILL sent to the whole unit kills the
watchdog too. Direction lines are left to the kernel (a dead process's line request is released; with the enable
input low the L298 lets the motor coast whatever the direction inputs read).
"""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

from drivers.gpiod.pwm import stop_pwm_channels

READY = b"ready\n"
START_TIMEOUT_S = 10.0


class PwmWatchdog:
    """The watchdog process for `channels` of the PWM chip at `chip`; started at once (blocking until it is ready)."""

    def __init__(self, chip: Path, channels: Sequence[int]) -> None:
        root = str(Path(__file__).resolve().parents[2])  # the directory holding the drivers package
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH")) if p)}
        self._process = subprocess.Popen(  # noqa: S603 - our own interpreter and module, arguments are numbers
            [sys.executable, "-m", "drivers.gpiod.watchdog", str(chip), *(str(c) for c in channels)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            start_new_session=True,
            env=env,
        )
        assert self._process.stdout is not None
        try:
            started, _, _ = select.select([self._process.stdout], [], [], START_TIMEOUT_S)
            ready = self._process.stdout.readline() if started else b""  # one short line, written first thing
        finally:
            self._process.stdout.close()
        if ready != READY:
            self.stop()
            raise RuntimeError(f"the PWM watchdog did not start (exit status {self._process.poll()})")

    @property
    def pid(self) -> int:
        """The watchdog's process id."""
        return self._process.pid

    def stop(self, timeout_s: float = 5.0) -> None:
        """Close the pipe (the watchdog stops the channels and exits) and wait for it."""
        if self._process.stdin is not None and not self._process.stdin.closed:
            self._process.stdin.close()
        try:
            self._process.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait()


def main(argv: Sequence[str]) -> int:
    """Wait for end of file on standard input, then stop the channels; 1 if a write failed."""
    for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(signum, signal.SIG_IGN)
    chip, channels = Path(argv[0]), [int(channel) for channel in argv[1:]]
    sys.stdout.buffer.write(READY)
    sys.stdout.flush()
    while sys.stdin.buffer.read(4096):
        pass
    problems = stop_pwm_channels(chip, channels)
    for problem in problems:
        print(f"robotd PWM watchdog: {problem}", file=sys.stderr)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
