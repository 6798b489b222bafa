"""systemd's notify protocol: READY=1, STATUS=, WATCHDOG=1 and STOPPING=1 datagrams to $NOTIFY_SOCKET.

Not under systemd (no NOTIFY_SOCKET) every call is a no-op, so the daemon calls these unconditionally.
A path starting with '@' names a socket in the abstract namespace (a leading NUL byte). The watchdog interval
comes from WATCHDOG_USEC, honoured only when WATCHDOG_PID is unset or names this process, as sd_watchdog_enabled
does; pings are due at half the interval so one late ping does not get the service killed.
"""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Mapping

log = logging.getLogger(__name__)


class Notifier:
    """Sends notifications to the service manager, or nothing when there is none."""

    def __init__(self, environ: Mapping[str, str] | None = None) -> None:
        env = os.environ if environ is None else environ
        self.address = _address(env.get("NOTIFY_SOCKET", ""))
        self.watchdog_s = _watchdog_interval(env)
        self._sock: socket.socket | None = None

    @property
    def enabled(self) -> bool:
        """True when a service manager listens."""
        return self.address is not None

    @property
    def watchdog_period_s(self) -> float | None:
        """How often to ping the watchdog (half its interval), or None when it is off."""
        return None if self.watchdog_s is None else self.watchdog_s / 2.0

    def notify(self, *assignments: str) -> bool:
        """Send `KEY=value` lines as one datagram; False when nothing was sent (no manager, or it failed)."""
        if self.address is None:
            return False
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._sock.sendto("\n".join(assignments).encode(), self.address)
        except OSError as error:  # the manager's socket is gone or full: never take the daemon down for it
            log.warning("sd_notify to %r failed: %s", self.address, error)
            return False
        return True

    def ready(self, status: str | None = None) -> bool:
        """Start-up is complete (Type=notify)."""
        return self.notify("READY=1", *([f"STATUS={status}"] if status else []))

    def status(self, text: str) -> bool:
        """A one-line status shown by `systemctl status`."""
        return self.notify(f"STATUS={_one_line(text)}")

    def watchdog(self) -> bool:
        """The service is alive (call only while the control loop and the filter are)."""
        return self.notify("WATCHDOG=1")

    def stopping(self, status: str | None = None) -> bool:
        """Shutdown has begun."""
        return self.notify("STOPPING=1", *([f"STATUS={_one_line(status)}"] if status else []))

    def close(self) -> None:
        """Release the socket."""
        if self._sock is not None:
            self._sock.close()
            self._sock = None


def _address(value: str) -> str | bytes | None:
    if not value:
        return None
    if value.startswith("@"):
        return b"\0" + value[1:].encode()
    if value.startswith("/"):
        return value
    log.warning("ignoring NOTIFY_SOCKET %r: neither a path nor an abstract socket", value)
    return None


def _watchdog_interval(env: Mapping[str, str]) -> float | None:
    pid = env.get("WATCHDOG_PID")
    if pid and pid != str(os.getpid()):
        return None
    try:
        usec = int(env.get("WATCHDOG_USEC", ""))
    except ValueError:
        return None
    return usec / 1e6 if usec > 0 else None


def _one_line(text: str) -> str:
    return " ".join(text.split())
