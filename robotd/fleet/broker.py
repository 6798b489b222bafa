"""A Mosquitto broker for one run (the virtual fleet, the tests): generated users, passwords and ACLs, on loopback.

Theory of operation. `BrokerSetup.write()` writes, in a private folder, one password per user (hashed by
`mosquitto_passwd -U`, so the broker never reads a clear password), an ACL with one block per robot (it may write its
own pose and status, and only read its own stop topic and the fleet's) and one for the operator (read and write the
whole tree: the viewer and the fleet stop), a `username:password` credentials file per user for robotd (mode 0600),
and `mosquitto.conf` (anonymous clients refused, one listener on 127.0.0.1, retained messages persisted in the folder
so a broker that restarts keeps its stops). `Broker` runs `mosquitto -c` on that file as a child process and waits
until it accepts connections; it can be stopped and started again on the same port (an outage).
"""

from __future__ import annotations

import contextlib
import os
import pwd
import secrets
import shutil
import signal
import socket
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

from robotd.fleet import topics

OPERATOR = "operator"
START_TIMEOUT_S = 10.0
STOP_GRACE_S = 5.0


def find_program(name: str) -> str | None:
    """The path of a Mosquitto program, also in the sbin folders a non-root PATH lacks, or None."""
    found = shutil.which(name)
    if found:
        return found
    for folder in ("/usr/sbin", "/usr/local/sbin", "/usr/bin", "/usr/local/bin"):
        path = Path(folder) / name
        if path.is_file() and os.access(path, os.X_OK):
            return str(path)
    return None


def robot_user(robot_id: str) -> str:
    """The broker user of a robot."""
    return f"robot-{robot_id}"


def robot_acl(robot_id: str) -> list[str]:
    """What a robot may do: publish its own pose and status, read its own stop and the fleet's."""
    return [
        f"user {robot_user(robot_id)}",
        f"topic write {topics.pose(robot_id)}",
        f"topic write {topics.status(robot_id)}",
        f"topic read {topics.stop(robot_id)}",
        f"topic read {topics.FLEET_STOP}",
    ]


def operator_acl() -> list[str]:
    """What the operator may do: watch every robot, and publish stops and releases."""
    return [f"user {OPERATOR}", f"topic readwrite {topics.ROOT}/#"]


def free_tcp_port() -> int:
    """A TCP port on loopback that nobody holds right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def _private(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    path.chmod(0o600)
    return path


@dataclass
class BrokerSetup:
    """The files of a broker for `robot_ids` in `folder` (see the module docstring)."""

    folder: Path
    robot_ids: tuple[str, ...]
    port: int = field(default_factory=free_tcp_port)
    passwords: dict[str, str] = field(default_factory=dict)

    @property
    def config_path(self) -> Path:
        """mosquitto.conf."""
        return self.folder / "mosquitto.conf"

    @property
    def url(self) -> str:
        """Where clients connect."""
        return f"mqtt://127.0.0.1:{self.port}"

    def credentials_file(self, user: str) -> Path:
        """The `username:password` file of a user (robotd's fleet.credentials_file)."""
        return self.folder / f"{user}.credentials"

    def write(self) -> None:
        """Write passwords, ACL, credentials files and mosquitto.conf (RuntimeError without mosquitto_passwd)."""
        passwd = find_program("mosquitto_passwd")
        if passwd is None:
            raise RuntimeError("mosquitto_passwd not found: install Debian's mosquitto package")
        self.folder.mkdir(parents=True, exist_ok=True)
        self.folder.chmod(0o700)
        users = [robot_user(robot_id) for robot_id in self.robot_ids] + [OPERATOR]
        for user in users:
            self.passwords.setdefault(user, secrets.token_urlsafe(18))
            _private(self.credentials_file(user), f"{user}:{self.passwords[user]}\n")
        password_file = _private(self.folder / "passwd", "".join(f"{u}:{self.passwords[u]}\n" for u in users))
        subprocess.run([passwd, "-U", str(password_file)], check=True, capture_output=True)  # noqa: S603
        blocks = [robot_acl(robot_id) for robot_id in self.robot_ids] + [operator_acl()]
        acl_file = _private(self.folder / "acl", "\n\n".join("\n".join(block) for block in blocks) + "\n")
        me = pwd.getpwuid(os.geteuid()).pw_name  # mosquitto started as root drops to this user: it must read our files
        conf = [
            "per_listener_settings false",
            "allow_anonymous false",
            f"password_file {password_file}",
            f"acl_file {acl_file}",
            f"listener {self.port} 127.0.0.1",
            "persistence true",
            f"persistence_location {self.folder}/",
            f"log_dest file {self.folder / 'mosquitto.log'}",
            "log_type error",
            "log_type warning",
            "log_type notice",
            f"user {me}",
        ]
        _private(self.config_path, "\n".join(conf) + "\n")


class Broker:
    """`mosquitto` on a BrokerSetup's config, as a child process (a context manager that always stops it)."""

    def __init__(self, setup: BrokerSetup) -> None:
        self.setup = setup
        self.proc: subprocess.Popen[bytes] | None = None

    def __enter__(self) -> Broker:
        self.start()
        return self

    def __exit__(self, *_exc: object) -> None:
        self.stop()

    def start(self) -> None:
        """Start mosquitto and wait until it accepts connections (RuntimeError when it cannot)."""
        program = find_program("mosquitto")
        if program is None:
            raise RuntimeError("mosquitto not found: install Debian's mosquitto package")
        if not self.setup.config_path.exists():
            self.setup.write()
        self.proc = subprocess.Popen(  # noqa: S603 - the broker with our generated configuration
            [program, "-c", str(self.setup.config_path)],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            process_group=0,  # a terminal's Ctrl-C reaches the parent, which stops the broker last
        )
        deadline = time.monotonic() + START_TIMEOUT_S
        while not self._accepting():
            if self.proc.poll() is not None:
                error = self.proc.stderr.read().decode(errors="replace").strip() if self.proc.stderr else ""
                self.proc = None
                raise RuntimeError(f"mosquitto exited at start: {error or 'see ' + str(self.setup.folder)}")
            if time.monotonic() > deadline:
                self.stop()
                raise RuntimeError(f"mosquitto did not listen on port {self.setup.port} within {START_TIMEOUT_S:g} s")
            time.sleep(0.02)

    def _accepting(self) -> bool:
        with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", self.setup.port), timeout=0.2):
            return True
        return False

    def stop(self) -> None:
        """SIGTERM (mosquitto saves its retained messages), SIGKILL after a grace period; reaped either way."""
        proc, self.proc = self.proc, None
        if proc is None:
            return
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(STOP_GRACE_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        if proc.stderr is not None:
            proc.stderr.close()
