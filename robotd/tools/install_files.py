"""Install steps for files and directories: exact content, mode and owner, compared before anything is written.

Owners are resolved by name in the root's own /etc/passwd and /etc/group (a throw-away root has its own ids). A file is
written to a temporary name beside it, given its mode and owner, and renamed into place, so nobody ever reads half a
file or a key with the wrong mode.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from robotd.tools.install_steps import InstallError, Kind, State, Target, kept


@dataclass(frozen=True, slots=True)
class Ownership:
    """Mode and owner a file or directory must have."""

    mode: int
    user: str = "root"
    group: str = "root"

    def problems(self, target: Target, info: os.stat_result) -> list[str]:
        """What differs: 'mode 0644 -> 0640', 'owner 0:0 -> root:robotd'."""
        found: list[str] = []
        if stat.S_IMODE(info.st_mode) != self.mode:
            found.append(f"mode {stat.S_IMODE(info.st_mode):04o} -> {self.mode:04o}")
        ids = target.ids(self.user, self.group)
        if ids is None or (info.st_uid, info.st_gid) != ids:
            found.append(f"owner {info.st_uid}:{info.st_gid} -> {self.user}:{self.group}")
        return found

    def set(self, target: Target, path: Path) -> None:
        """chmod and chown (ids as the root knows the names)."""
        ids = target.ids(self.user, self.group)
        if ids is None:
            raise InstallError(f"{path}: no user {self.user} or group {self.group} in {target.path('/etc')}")
        os.chown(path, *ids)
        path.chmod(self.mode)

    def describe(self) -> str:
        """'mode 0640 root:robotd'."""
        return f"mode {self.mode:04o} {self.user}:{self.group}"


@dataclass(frozen=True, slots=True)
class Directory:
    """A directory with its mode and owner (kept on uninstall: it holds the configuration)."""

    path: str
    owner: Ownership
    keep_reason: str
    removal_phase: int = 4
    topic: str = "config"

    def check(self, target: Target) -> State:
        """In place when it exists with the right mode and owner."""
        where = target.path(self.path)
        if not where.is_dir():
            return State(Kind.CHANGE, f"create {self.path} ({self.owner.describe()})")
        problems = self.owner.problems(target, where.stat())
        if problems:
            return State(Kind.CHANGE, f"set {', '.join(problems)} of {self.path}")
        return State(Kind.IN_PLACE, f"{self.path} ({self.owner.describe()})")

    def apply(self, target: Target) -> None:
        """mkdir, chmod, chown."""
        where = target.path(self.path)
        where.mkdir(parents=True, exist_ok=True)
        self.owner.set(target, where)

    def check_removal(self, _target: Target) -> State:
        """Always kept."""
        return kept(f"{self.path} ({self.keep_reason})")

    def remove(self, target: Target) -> None:
        """Kept."""


def write_atomically(path: Path, content: bytes, owner: Ownership, target: Target) -> None:
    """Write `content` to `path` whole or not at all, mode and owner set before it appears."""
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.robotd-install")
    fd = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW, 0o600)
    try:
        with os.fdopen(fd, "wb") as stream:
            stream.write(content)
            stream.flush()
            os.fsync(stream.fileno())
        owner.set(target, temporary)
        temporary.replace(path)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


@dataclass(frozen=True, slots=True)
class File:
    """A file with exact content, mode and owner; `keep_reason` keeps it on uninstall (and keeps an edited copy)."""

    path: str
    content: bytes
    owner: Ownership
    topic: str  # what a change concerns: "units", "udev" or "config" (drives reloads and restarts)
    keep_reason: str | None = None  # None: removed on uninstall, and replaced when its content differs
    prune_parent: bool = False  # on removal, remove the parent directory too when it is left empty

    @property
    def removal_phase(self) -> int:
        """Removed with the files, or kept last."""
        return 2 if self.keep_reason is None else 4

    def check(self, target: Target) -> State:
        """In place when it exists with this content (or is kept as edited), mode and owner."""
        where = target.path(self.path)
        if not where.is_file():
            return State(Kind.CHANGE, f"install {self.path} ({self.owner.describe()})")
        if self.keep_reason is None and where.read_bytes() != self.content:
            return State(Kind.CHANGE, f"update {self.path} (content differs)")
        problems = self.owner.problems(target, where.stat())
        if problems:
            return State(Kind.CHANGE, f"set {', '.join(problems)} of {self.path}")
        edited = self.keep_reason is not None and where.read_bytes() != self.content
        return State(Kind.IN_PLACE, f"{self.path}{' (edited: kept as it is)' if edited else ''}")

    def apply(self, target: Target) -> None:
        """Write the content when missing (or different, unless kept), then set mode and owner."""
        where = target.path(self.path)
        if not where.is_file() or (self.keep_reason is None and where.read_bytes() != self.content):
            write_atomically(where, self.content, self.owner, target)
        else:
            self.owner.set(target, where)

    def check_removal(self, target: Target) -> State:
        """Kept, or removed when present."""
        if self.keep_reason is not None:
            return kept(f"{self.path} ({self.keep_reason})")
        if target.path(self.path).exists():
            return State(Kind.CHANGE, f"remove {self.path}")
        return State(Kind.IN_PLACE, f"{self.path} absent")

    def remove(self, target: Target) -> None:
        """Unlink (and prune the emptied parent)."""
        where = target.path(self.path)
        where.unlink(missing_ok=True)
        if self.prune_parent and where.parent.is_dir() and not any(where.parent.iterdir()):
            where.parent.rmdir()


@dataclass(frozen=True, slots=True)
class KeyFile:
    """A secret made fresh when missing and never replaced (the remote controls hold a copy); kept on uninstall."""

    path: str
    owner: Ownership
    keep_reason: str
    fresh: Callable[[], bytes]
    problems: Callable[[Path], list[str]]  # what is wrong with an existing key's content
    removal_phase: int = 4
    topic: str = "config"

    def check(self, target: Target) -> State:
        """In place when a valid key is there with the right mode and owner; BLOCKED when it holds no valid key."""
        where = target.path(self.path)
        if not where.exists():
            return State(Kind.CHANGE, f"create a fresh key {self.path} ({self.owner.describe()})")
        bad = self.problems(where)
        if bad:
            return State(Kind.BLOCKED, f"{bad[0]}: robotd install never replaces a key; delete it to get a fresh one")
        problems = self.owner.problems(target, where.stat())
        if problems:
            return State(Kind.CHANGE, f"set {', '.join(problems)} of {self.path}")
        return State(Kind.IN_PLACE, f"{self.path} ({self.owner.describe()})")

    def apply(self, target: Target) -> None:
        """Write a fresh key when none is there, then set mode and owner."""
        where = target.path(self.path)
        if where.exists():
            self.owner.set(target, where)
        else:
            write_atomically(where, self.fresh(), self.owner, target)

    def check_removal(self, _target: Target) -> State:
        """Always kept."""
        return kept(f"{self.path} ({self.keep_reason})")

    def remove(self, target: Target) -> None:
        """Kept."""
