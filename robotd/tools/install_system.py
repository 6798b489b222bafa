"""Install steps that talk to systemd and udev: enable, start, reload, verify (see robotd.tools.install_steps).

Under a throw-away root, enabling runs for real (`systemctl --root=ROOT` makes the symbolic links offline); starting,
stopping and reloading act on the running system, so they are recorded instead. On a system where systemd is not
running (a container, an image being built) they are recorded too.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass

from robotd.tools.install_steps import Kind, State, Target

UNIT_DIRS = ("/etc/systemd/system", "/lib/systemd/system", "/usr/lib/systemd/system")


def systemd_running(target: Target) -> bool:
    """True when the target is the running system and systemd runs it."""
    return target.live and target.path("/run/systemd/system").is_dir()


def unit_installed(target: Target, unit: str) -> bool:
    """True when a unit file of that name is in one of the root's unit directories."""
    return any(target.path(f"{directory}/{unit}").is_file() for directory in UNIT_DIRS)


def _query(target: Target, *args: str) -> list[str]:
    """The words a read-only systemctl query printed (none when systemctl is missing)."""
    return target.run(target.systemctl(*args)).stdout.split()


def _not_run(target: Target, command: str) -> State:
    why = "under --root the running system is not touched" if not target.live else "systemd is not running here"
    return State(Kind.RECORD, f"{command}  ({why})")


@dataclass(frozen=True, slots=True)
class UnitsEnabled:
    """Units enabled at boot (offline under --root)."""

    units: tuple[str, ...]
    removal_phase: int = 1
    topic: str = ""

    def _enabled(self, target: Target) -> list[str]:
        return [unit for unit in self.units if _query(target, "is-enabled", unit) == ["enabled"]]

    def check(self, target: Target) -> State:
        """In place when every unit is enabled."""
        missing = [unit for unit in self.units if unit not in self._enabled(target)]
        if missing:
            return State(Kind.CHANGE, f"enable {' '.join(missing)} at boot")
        return State(Kind.IN_PLACE, f"{' '.join(self.units)} enabled at boot")

    def apply(self, target: Target) -> None:
        """systemctl enable."""
        missing = [unit for unit in self.units if unit not in self._enabled(target)]
        target.call(target.systemctl("enable", *missing))

    def check_removal(self, target: Target) -> State:
        """Disable what is enabled."""
        enabled = self._enabled(target)
        if enabled:
            return State(Kind.CHANGE, f"disable {' '.join(enabled)}")
        return State(Kind.IN_PLACE, f"{' '.join(self.units)} not enabled")

    def remove(self, target: Target) -> None:
        """systemctl disable."""
        target.call(target.systemctl("disable", *self._enabled(target)))


@dataclass(frozen=True, slots=True)
class UnitsRunning:
    """Units running now; restarted when their unit files or the configuration changed in this run."""

    units: tuple[str, ...]
    removal_phase: int = 0
    topic: str = ""

    def _inactive(self, target: Target) -> list[str]:
        return [unit for unit in self.units if _query(target, "is-active", unit) != ["active"]]

    def _restart(self, target: Target) -> bool:
        return bool(target.changed & {"units", "config"})

    def _action(self, target: Target) -> list[str] | None:
        """The systemctl command that brings the units up to date, or None when they are."""
        if self._restart(target):
            return ["restart", *self.units]  # also starts what is not running
        inactive = self._inactive(target)
        return ["start", *inactive] if inactive else None

    def check(self, target: Target) -> State:
        """In place when every unit is active and nothing it reads changed in this run."""
        if not systemd_running(target):
            verb = "restart" if self._restart(target) else "start"
            return _not_run(target, f"systemctl {verb} {' '.join(self.units)}")
        action = self._action(target)
        if action is None:
            return State(Kind.IN_PLACE, f"{' '.join(self.units)} running")
        why = " (unit files or configuration changed)" if action[0] == "restart" else ""
        return State(Kind.CHANGE, f"{' '.join(action)}{why}")

    def apply(self, target: Target) -> None:
        """systemctl start what is not running, or restart everything after a change."""
        action = self._action(target)
        if action is not None:
            target.call(target.systemctl(*action))

    def check_removal(self, target: Target) -> State:
        """Stop what runs."""
        if not systemd_running(target):
            return _not_run(target, f"systemctl stop {' '.join(reversed(self.units))}")
        active = [unit for unit in self.units if unit not in self._inactive(target)]
        if active:
            return State(Kind.CHANGE, f"stop {' '.join(reversed(active))}")
        return State(Kind.IN_PLACE, f"{' '.join(self.units)} not running")

    def remove(self, target: Target) -> None:
        """systemctl stop (the robot's service first)."""
        target.call(target.systemctl("stop", *reversed(self.units)))


@dataclass(frozen=True, slots=True)
class DaemonReload:
    """systemd re-reads unit files that changed in this run."""

    removal_phase: int = 3
    topic: str = ""

    def check(self, target: Target) -> State:
        """A reload is due after a unit file changed."""
        if "units" not in target.changed:
            return State(Kind.IN_PLACE, "unit files unchanged: no daemon-reload")
        if not systemd_running(target):
            return _not_run(target, "systemctl daemon-reload")
        return State(Kind.CHANGE, "systemctl daemon-reload")

    def apply(self, target: Target) -> None:
        """systemctl daemon-reload."""
        target.call(target.systemctl("daemon-reload"))

    def check_removal(self, target: Target) -> State:
        """The same after unit files were removed."""
        return self.check(target)

    def remove(self, target: Target) -> None:
        """systemctl daemon-reload."""
        self.apply(target)


UDEV_RELOAD = ("udevadm control --reload", "udevadm trigger --subsystem-match=tty --action=add")


@dataclass(frozen=True, slots=True)
class UdevReload:
    """udev re-reads its rules after ours changed and re-announces serial devices, so the link appears."""

    removal_phase: int = 3
    topic: str = ""

    def check(self, target: Target) -> State:
        """A reload is due after the rule changed."""
        if "udev" not in target.changed:
            return State(Kind.IN_PLACE, "udev rules unchanged: no reload")
        if not target.live or not target.path("/run/udev").is_dir():
            why = "under --root the running system is not touched" if not target.live else "udev is not running"
            return State(Kind.RECORD, f"{'; '.join(UDEV_RELOAD)}  ({why})")
        return State(Kind.CHANGE, "; ".join(UDEV_RELOAD))

    def apply(self, target: Target) -> None:
        """udevadm control --reload, then trigger the tty devices."""
        for command in UDEV_RELOAD:
            target.call(command.split())

    def check_removal(self, target: Target) -> State:
        """The same after the rule was removed."""
        return self.check(target)

    def remove(self, target: Target) -> None:
        """Reload and trigger."""
        self.apply(target)


@dataclass(frozen=True, slots=True)
class VerifyUnit:
    """`systemd-analyze verify` on the installed unit, before it is enabled (skipped when the tool is missing)."""

    unit: str
    removal_phase: int = 4
    topic: str = ""

    def check(self, target: Target) -> State:
        """In place when the verifier is content; BLOCKED with its complaint otherwise."""
        installed = target.path(f"/etc/systemd/system/{self.unit}")
        if shutil.which("systemd-analyze") is None:
            return State(Kind.IN_PLACE, f"{self.unit} not verified: systemd-analyze is not installed")
        if not installed.is_file():
            return State(Kind.IN_PLACE, f"{self.unit} will be verified once installed")
        search = ":".join(str(target.path(directory)) for directory in UNIT_DIRS)
        result = target.run(
            ["env", f"SYSTEMD_UNIT_PATH={search}:", "SYSTEMD_LOG_COLOR=0", "systemd-analyze", "verify", str(installed)]
        )
        complaint = (result.stderr or result.stdout).strip()
        if result.returncode != 0 or complaint:
            return State(
                Kind.BLOCKED, f"systemd-analyze verify {self.unit}: {complaint or f'exit {result.returncode}'}"
            )
        return State(Kind.IN_PLACE, f"{self.unit} passes systemd-analyze verify")

    def apply(self, _target: Target) -> None:
        """Nothing to apply: a complaint stops the installation (BLOCKED)."""

    def check_removal(self, _target: Target) -> State:
        """Nothing to undo."""
        return State(Kind.IN_PLACE, f"{self.unit}: nothing to verify")

    def remove(self, target: Target) -> None:
        """Nothing to undo."""
