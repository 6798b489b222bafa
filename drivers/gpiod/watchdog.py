"""A small process that stops the RP1's PWM when its owner dies, stops or hangs: the gpiod back-end's deadman.

Theory of operation: the motors' owner starts `python -m drivers.gpiod.watchdog CHIP CHANNEL...` with a pipe on its
standard input and one on its standard output, and keeps their other ends. On standard input the owner writes one
byte per control period (drivers.gpiod.heartbeat: heartbeat, disarm, closing); the watchdog runs the heartbeat
state machine on what it reads:
- no heartbeat for `--timeout-s` once armed (the owner SIGSTOPped, its loop hung, or too busy to keep its period):
  every channel's duty_cycle goes to 0 (enable stays on, so the owner can drive again; duty 0 holds the pin low),
  then the direction lines are driven low when the watchdog can take them (not while a live owner holds them: the
  L298 coasts with its enable low whatever they read), and `trip N` is written on standard output for the owner to
  read. The next heartbeat re-arms it, as the pigpio deadman script does.
- end of file (the owner closed the pipe, or the kernel closed it for an owner that died: SIGKILL, a crash, the OOM
  killer): duty 0 and enable 0 on every channel (drivers.gpiod.pwm.stop_pwm_channels) and, unless the owner said it
  was closing cleanly, the direction lines low once the dead owner's request is released; then it exits.
It runs in its own session and ignores SIGINT, SIGTERM and SIGHUP: a Ctrl-C or systemd's stop reach the owner, which
zeroes its motors itself; its pipe then closes and the watchdog follows. A SIGSTOP sent to the owner's process group
does not reach it.

Not a substitute for systemd's ExecStopPost (`robotd stop-motors`): a SIGKILL sent to the whole unit kills the
watchdog too. The watchdog itself stopped or killed by hand: the owner sees its standard output close (a lost
deadman) only in the latter case.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import os
import select
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from drivers.gpiod.heartbeat import CLOSING, DISARM, HEARTBEAT, HeartbeatMonitor
from drivers.gpiod.lines import OutputLinesOpener, open_output_lines
from drivers.gpiod.pwm import SYSFS, Attributes, stop_pwm_channels

READY = b"ready\n"
START_TIMEOUT_S = 10.0
RELEASE_WAIT_S = 0.5
"""How long a dead owner's direction lines may stay held after its pipe closed (the kernel closes its files one by
one)."""


class PwmWatchdog:
    """The watchdog process for `channels` of the PWM chip at `chip`; started at once (blocking until it is ready).

    `timeout_s` None: it guards the owner's death only. Otherwise `heartbeat()` arms it and keeps it armed.
    """

    def __init__(
        self,
        chip: Path,
        channels: Sequence[int],
        *,
        timeout_s: float | None = None,
        direction_pins: Sequence[int] = (),
        gpio_chip: str | None = None,
    ) -> None:
        root = str(Path(__file__).resolve().parents[2])  # the directory holding the drivers package
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH")) if p)}
        options = [f"--timeout-s={timeout_s!r}"] if timeout_s is not None else []
        if direction_pins:
            options.append(f"--direction-pins={','.join(map(str, direction_pins))}")
        if gpio_chip:
            options.append(f"--gpio-chip={gpio_chip}")
        self._process = subprocess.Popen(  # noqa: S603 - our own interpreter and module, arguments are ours
            [sys.executable, "-m", "drivers.gpiod.watchdog", *options, str(chip), *(str(c) for c in channels)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            bufsize=0,
            start_new_session=True,
            env=env,
        )
        assert self._process.stdin is not None
        assert self._process.stdout is not None
        self._heartbeat_fd = self._process.stdin.fileno()
        self.reports_fd = self._process.stdout.fileno()
        """Readable when the watchdog reported something (`read_reports`) or exited."""
        self._pending = b""
        if self._read_ready() != READY:
            self.stop()
            raise RuntimeError(f"the PWM watchdog did not start (exit status {self._process.poll()})")
        os.set_blocking(self._heartbeat_fd, False)  # a heartbeat never waits for a watchdog that does not read
        os.set_blocking(self.reports_fd, False)

    def _read_ready(self) -> bytes:
        """The first line, written first thing, within START_TIMEOUT_S; b'' if none."""
        deadline = time.monotonic() + START_TIMEOUT_S
        line = b""
        while not line.endswith(b"\n"):
            started, _, _ = select.select([self.reports_fd], [], [], max(0.0, deadline - time.monotonic()))
            chunk = os.read(self.reports_fd, 64) if started else b""
            if not chunk:
                return b""
            line += chunk
        line, _, self._pending = line.partition(b"\n")
        return line + b"\n"

    @property
    def pid(self) -> int:
        """The watchdog's process id."""
        return self._process.pid

    def heartbeat(self) -> bool:
        """Tell the watchdog the owner is alive (arms it); False when it could not be told (never blocks)."""
        return self._send(HEARTBEAT)

    def disarm(self) -> bool:
        """Back to guarding death only, until the next heartbeat; False when it could not be told."""
        return self._send(DISARM)

    def _send(self, code: bytes) -> bool:
        try:
            return os.write(self._heartbeat_fd, code) == 1
        except OSError:  # full (a watchdog that does not read), closed, or the watchdog gone: its report says so
            return False

    def read_reports(self) -> list[int] | None:
        """The trip counts the watchdog reported since the last call (never blocks); None once it has exited."""
        try:
            chunk = os.read(self.reports_fd, 4096)
        except BlockingIOError:
            chunk = b"-"  # nothing new, not the end
        except OSError:
            return None
        if not chunk:
            return None
        if chunk != b"-":
            self._pending += chunk
        *lines, self._pending = self._pending.split(b"\n")
        return [int(line.split()[1]) for line in lines if line.startswith(b"trip ")]

    def exit_status(self) -> int | None:
        """The watchdog's exit status, None while it runs."""
        return self._process.poll()

    def stop(self, timeout_s: float = 5.0) -> None:
        """Say a clean close follows, close the pipe (the watchdog stops the channels and exits) and wait for it."""
        stdin, stdout = self._process.stdin, self._process.stdout
        if stdin is not None and not stdin.closed:
            self._send(CLOSING)
            with contextlib.suppress(OSError):
                stdin.close()
        try:
            self._process.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait()
        if stdout is not None:
            stdout.close()


# --- the watchdog process ---------------------------------------------------------------------------------------


def zero_pwm_duties(chip: Path, channels: Sequence[int], attributes: Attributes = SYSFS) -> list[str]:
    """duty_cycle 0 on each exported channel, enable left on (a trip: the owner may drive again); the failures."""
    problems = []
    for channel in channels:
        path = chip / f"pwm{channel}"
        if not path.is_dir():
            continue
        try:
            attributes.write(path / "duty_cycle", "0")
        except OSError as error:
            problems.append(f"{path / 'duty_cycle'}: {error.strerror or error}")
    return problems


def lower_direction_pins(
    pins: Sequence[int],
    gpio_chip: str | None,
    *,
    open_outputs: OutputLinesOpener = open_output_lines,
    wait_s: float = 0.0,
    sleep: Callable[[float], None] = time.sleep,
) -> str | None:
    """Drive `pins` low and let them go, retrying for `wait_s` while another request holds them; why not, or None."""
    deadline = time.monotonic() + wait_s
    while True:
        try:
            outputs = open_outputs(list(pins), gpio_chip)
        except OSError as error:  # GpioUnavailableError is one
            if error.errno == errno.EBUSY and time.monotonic() < deadline:
                sleep(0.01)
                continue
            return f"direction pins left as they are: {error}"
        try:
            outputs.set_values(dict.fromkeys(pins, 0))
        finally:
            outputs.release()
        return None


def _say(problems: Sequence[str]) -> None:
    for problem in problems:
        print(f"robotd PWM watchdog: {problem}", file=sys.stderr, flush=True)


def _report(line: str) -> None:
    with contextlib.suppress(OSError):  # an owner that is gone reads nothing
        sys.stdout.buffer.write(line.encode() + b"\n")
        sys.stdout.flush()


def main(argv: Sequence[str]) -> int:
    """Run the heartbeat deadman on standard input until end of file, then stop the channels; 1 if a write failed."""
    for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(signum, signal.SIG_IGN)
    parser = argparse.ArgumentParser(prog="python -m drivers.gpiod.watchdog")
    parser.add_argument("chip", type=Path)
    parser.add_argument("channels", type=int, nargs="+")
    parser.add_argument("--timeout-s", type=float, default=None)
    parser.add_argument("--direction-pins", default="")
    parser.add_argument("--gpio-chip", default=None)
    args = parser.parse_args(argv)
    directions = [int(pin) for pin in args.direction_pins.split(",") if pin]
    monitor = HeartbeatMonitor(args.timeout_s)
    sys.stdout.buffer.write(READY)
    sys.stdout.flush()
    stdin = sys.stdin.fileno()
    said: str | None = None  # the last note on the direction pins: said once, not at every trip
    while True:
        readable, _, _ = select.select([stdin], [], [], monitor.wait_s(time.monotonic()))
        if readable:
            data = os.read(stdin, 4096)
            if not data:
                break
            monitor.feed(data, time.monotonic())
        if monitor.expired(time.monotonic()):
            problems = zero_pwm_duties(args.chip, args.channels)
            note = lower_direction_pins(directions, args.gpio_chip) if directions else None
            _say([*problems, *([note] if note and note != said else [])])
            said = note
            _report(f"trip {monitor.trips}")
    problems = stop_pwm_channels(args.chip, args.channels)
    if directions and not monitor.closing:
        note = lower_direction_pins(directions, args.gpio_chip, wait_s=RELEASE_WAIT_S)
        _say([note] if note else [])
    _say(problems)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
