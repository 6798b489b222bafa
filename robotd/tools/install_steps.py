"""The steps of `robotd install` and `robotd uninstall`: each says what it is, whether it is in place, how to apply it.

Theory of operation: install and uninstall share one list of small step objects. `check` only reads: in place ->
"unchanged"; otherwise --dry-run prints what the step would do and a real run applies it. Files are compared by
content, mode and owner before anything is written, so a second run changes nothing and says so. On uninstall each
step is either removed (units, the udev rule) or kept with its reason (the configuration, the key, the user and group
that own them). Every path lives under `Target.root`: "/" on the robot, a throw-away directory in tests. There the
tools get `--prefix ROOT` and `systemctl --root=ROOT`, and what only the running system can do (start a service,
reload udev) is recorded and printed, never run.
"""

from __future__ import annotations

import enum
import shutil
import subprocess
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

Runner = Callable[[Sequence[str]], "subprocess.CompletedProcess[str]"]


def run_command(argv: Sequence[str]) -> subprocess.CompletedProcess[str]:
    """Run a system tool, capturing its output; a missing tool exits 127 and a hung one 124, as a shell says."""
    if shutil.which(argv[0]) is None:
        return subprocess.CompletedProcess(list(argv), 127, "", f"{argv[0]}: not installed here")
    try:
        return subprocess.run(list(argv), capture_output=True, text=True, timeout=120, check=False)  # noqa: S603
    except subprocess.TimeoutExpired:
        return subprocess.CompletedProcess(list(argv), 124, "", f"{argv[0]}: no answer in 120 s")


class InstallError(Exception):
    """A step cannot be applied; the message says why and what to do."""


class Kind(enum.Enum):
    """What a step's check found."""

    IN_PLACE = "unchanged"
    KEPT = "kept"  # uninstall leaves it, on purpose
    CHANGE = "change"
    RECORD = "not run"  # acts on the running system: only recorded under a throw-away root
    BLOCKED = "blocked"  # cannot be applied until the person fixes something


@dataclass(frozen=True, slots=True)
class State:
    """A step's check: what is there (in place) or what applying it does."""

    kind: Kind
    what: str


@dataclass
class Target:
    """Where to install ("/" on the robot) and how to run tools; remembers what this run changed."""

    root: Path
    run: Runner = run_command
    changed: set[str] = field(default_factory=set)  # topics changed so far: "units", "udev", "config"
    recorded: list[str] = field(default_factory=list)  # commands for the running system, not run under --root

    @property
    def live(self) -> bool:
        """True when installing into the running system."""
        return self.root.resolve() == Path("/")

    def path(self, absolute: str) -> Path:
        """`absolute` (a path on the robot) inside the root."""
        return self.root / absolute.lstrip("/")

    def prefix(self) -> list[str]:
        """The user tools' option to edit the root's /etc instead of this system's."""
        return [] if self.live else ["--prefix", str(self.root)]

    def systemctl(self, *args: str) -> list[str]:
        """A systemctl command line for this root (offline with --root under a throw-away root)."""
        return ["systemctl", *([] if self.live else [f"--root={self.root}"]), *args]

    def call(self, argv: Sequence[str]) -> subprocess.CompletedProcess[str]:
        """Run a tool that must succeed, or raise InstallError with its message."""
        result = self.run(argv)
        if result.returncode != 0:
            reason = (result.stderr or result.stdout).strip().splitlines()
            raise InstallError(f"`{' '.join(argv)}` failed: {reason[-1] if reason else f'exit {result.returncode}'}")
        return result

    def database(self, name: str) -> dict[str, list[str]]:
        """The root's /etc/passwd or /etc/group as name -> fields ({} when absent)."""
        try:
            text = self.path(f"/etc/{name}").read_text(encoding="utf-8")
        except FileNotFoundError:
            return {}
        entries = (line.split(":") for line in text.splitlines() if line and not line.startswith("#"))
        return {fields[0]: fields for fields in entries if len(fields) >= 4}

    def ids(self, user: str, group: str) -> tuple[int, int] | None:
        """The numeric owner for user:group as the root knows them, or None when either does not exist yet."""
        users, groups = self.database("passwd"), self.database("group")
        if user not in users or group not in groups:
            return None
        return int(users[user][2]), int(groups[group][2])


class Step(Protocol):
    """One idempotent piece of the installation."""

    @property
    def removal_phase(self) -> int:
        """Uninstall order: services first (0, 1), then files (2), then reloads (3), then what is kept (4)."""
        ...

    @property
    def topic(self) -> str:
        """What a change of this step concerns ("units", "udev", "config" or ""): reloads and restarts follow it."""
        ...

    def check(self, _target: Target) -> State:
        """What is in place, or what applying would do (reads only)."""
        ...

    def apply(self, _target: Target) -> None:
        """Bring this piece into place."""
        ...

    def check_removal(self, _target: Target) -> State:
        """What uninstalling would do: CHANGE to remove, IN_PLACE when nothing is there or it is kept."""
        ...

    def remove(self, target: Target) -> None:
        """Undo this piece."""
        ...


def kept(what: str) -> State:
    """What uninstall leaves in place, on purpose."""
    return State(Kind.KEPT, what)


@dataclass(frozen=True, slots=True)
class Require:
    """A precondition checked before anything changes (a tool, a package, a file)."""

    label: str
    holds: Callable[[Target], bool]
    fix: str
    removal_phase: int = 4
    topic: str = ""

    def check(self, target: Target) -> State:
        """In place when the precondition holds, else BLOCKED with the fix."""
        return State(Kind.IN_PLACE, self.label) if self.holds(target) else State(Kind.BLOCKED, self.fix)

    def apply(self, _target: Target) -> None:
        """A precondition cannot be applied: the person has to fix it."""
        raise InstallError(self.fix)

    def check_removal(self, _target: Target) -> State:
        """Nothing to undo."""
        return State(Kind.IN_PLACE, self.label)

    def remove(self, target: Target) -> None:
        """Nothing to undo."""


@dataclass(frozen=True, slots=True)
class Group:
    """A system group (created when missing, never deleted: files may still carry its id)."""

    name: str
    keep_reason: str
    removal_phase: int = 4
    topic: str = ""

    def check(self, target: Target) -> State:
        """In place when the root's /etc/group has it."""
        if self.name in target.database("group"):
            return State(Kind.IN_PLACE, f"group {self.name}")
        return State(Kind.CHANGE, f"create system group {self.name}")

    def apply(self, target: Target) -> None:
        """groupadd --system."""
        target.call(["groupadd", "--system", *target.prefix(), self.name])

    def check_removal(self, _target: Target) -> State:
        """Always kept."""
        return kept(f"group {self.name} ({self.keep_reason})")

    def remove(self, target: Target) -> None:
        """Kept."""


@dataclass(frozen=True, slots=True)
class User:
    """The service's system user: no login, its own group, member of the device groups."""

    name: str
    home: str
    groups: tuple[str, ...]
    keep_reason: str
    removal_phase: int = 4
    topic: str = ""

    def _missing_groups(self, target: Target) -> list[str]:
        groups = target.database("group")
        return [g for g in self.groups if self.name not in groups.get(g, ["", "", "", ""])[3].split(",")]

    def check(self, target: Target) -> State:
        """In place when the user exists and belongs to every group."""
        if self.name not in target.database("passwd"):
            return State(
                Kind.CHANGE,
                f"create system user {self.name} (group {self.name}, home {self.home}, no login shell, "
                f"also in {', '.join(self.groups)})",
            )
        missing = self._missing_groups(target)
        if missing:
            return State(Kind.CHANGE, f"add user {self.name} to {', '.join(missing)}")
        return State(Kind.IN_PLACE, f"user {self.name} in {', '.join(self.groups)}")

    def apply(self, target: Target) -> None:
        """useradd --system, or usermod --append for the missing groups."""
        if self.name not in target.database("passwd"):
            target.call(
                ["useradd", "--system", *target.prefix(), "--home-dir", self.home, "--no-create-home",
                 "--shell", "/usr/sbin/nologin", "--gid", self.name, "--groups", ",".join(self.groups), self.name]
            )  # fmt: skip
        else:
            missing = self._missing_groups(target)
            target.call(["usermod", *target.prefix(), "--append", "--groups", ",".join(missing), self.name])

    def check_removal(self, _target: Target) -> State:
        """Always kept."""
        return kept(f"user {self.name} ({self.keep_reason})")

    def remove(self, target: Target) -> None:
        """Kept."""
