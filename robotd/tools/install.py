"""`robotd install` / `robotd uninstall`: the robot's service set up from a robotd checkout, idempotently.

The plan is one list of steps (robotd.tools.install_steps): preconditions first, so a missing tool or package stops
the installation before anything changes; then the service user and groups, /etc/robotd with the configuration and a
fresh teleop key, the beacon's udev rule, the systemd units (pigpiod's drop-in on a board that runs pigpio), and
last enabling and starting them. Uninstalling walks the same list: it stops and disables the services, removes the
units and the rule, and keeps the configuration, the key, the user and group that own them, and the logs.
"""

from __future__ import annotations

import base64
import secrets
import shutil
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from drivers.gpiod.lines import GPIOD_MINIMUM, gpiod_new_enough, gpiod_version
from robotd.config.model import parse
from robotd.config.schema import ConfigError
from robotd.daemon.teleop import load_key
from robotd.tools.host import Board
from robotd.tools.install_files import Directory, File, KeyFile, Ownership
from robotd.tools.install_steps import Group, InstallError, Kind, Require, State, Step, Target, User
from robotd.tools.install_system import (
    DaemonReload,
    UdevReload,
    UnitsEnabled,
    UnitsRunning,
    VerifyUnit,
    unit_installed,
)

SERVICE_USER = "robotd"
CONFIG_DIR = "/etc/robotd"
CONFIG_PATH = "/etc/robotd/robot.yaml"
KEY_PATH = "/etc/robotd/teleop.key"
HOME = "/var/lib/robotd"
UDEV_RULE = "/etc/udev/rules.d/99-marvelmind.rules"
UNIT = "/etc/systemd/system/robotd.service"
DROP_IN = "/etc/systemd/system/pigpiod.service.d/robotd.conf"
SHIPPED_ROBOTD = "/opt/robotd/.venv/bin/robotd"
"""The program path written in systemd/robotd.service; the installed unit names the robotd actually installed."""
BEACON_USB_VENDOR = "0483"  # the generic STM32 id Marvelmind beacons use: the serial number tells them apart
DEVICE_GROUPS = ("gpio", "dialout")  # /dev/gpiomem and /dev/gpiochip*, the beacon's serial device
KEPT_LOGS = "the logs: journalctl -u robotd, and /var/lib/robotd"


@dataclass(frozen=True, slots=True)
class Options:
    """What to install: from which checkout, for which board, which beacon, running which robotd program."""

    source: Path  # a robotd checkout: config/robot.yaml and systemd/
    board: Board
    beacon_serial: str | None
    robotd_path: str


def find_source(candidates: list[Path]) -> Path | None:
    """The first directory holding config/robot.yaml and systemd/robotd.service, or None."""
    for candidate in candidates:
        if (candidate / "config" / "robot.yaml").is_file() and (candidate / "systemd" / "robotd.service").is_file():
            return candidate
    return None


def render_unit(text: str, robotd_path: str, *, pigpio: bool) -> str:
    """The shipped unit for this robot: its robotd program, and without pigpiod on a board that cannot run it."""
    text = text.replace(SHIPPED_ROBOTD, robotd_path)
    if pigpio:
        return text
    lines = []
    section = ""
    for line in text.splitlines():
        key, _, value = line.partition("=")
        section = line if line.startswith("[") else section
        if section == "[Unit]" and line.startswith("#") and "pigpiod" in line:  # the comment on the dependency
            continue
        if key in ("Requires", "After") and "pigpiod.service" in value.split():
            kept = [unit for unit in value.split() if unit != "pigpiod.service"]
            if not kept:
                continue
            lines.append(f"{key}={' '.join(kept)}")
            continue
        lines.append(line)
    return "\n".join(lines) + "\n"


def udev_rule(serial: str) -> str:
    """The rule that links the beacon with this USB serial number at /dev/marvelmind, readable by dialout."""
    return (
        f"# robotd: the Marvelmind beacon with USB serial number {serial} at /dev/marvelmind (robotd install)\n"
        f'SUBSYSTEM=="tty", ATTRS{{idVendor}}=="{BEACON_USB_VENDOR}", ATTRS{{serial}}=="{serial}", '
        'SYMLINK+="marvelmind", GROUP="dialout", MODE="0660"\n'
    )


def fresh_key() -> bytes:
    """A new teleop key: 32 random bytes, base64 (the README's `head -c 32 /dev/urandom | base64`)."""
    return base64.b64encode(secrets.token_bytes(32)) + b"\n"


def key_problems(path: Path) -> list[str]:
    """What is wrong with a key file's content (its mode and owner are the step's to fix)."""
    try:
        load_key(path)
    except ConfigError as error:
        return error.problems
    return []


def _have(*tools: str) -> Callable[[Target], bool]:
    return lambda _target: all(shutil.which(tool) for tool in tools)


def _preconditions(board: Board) -> list[Step]:
    steps: list[Step] = [
        Require("useradd, usermod and groupadd found", _have("useradd", "usermod", "groupadd"),
                "useradd, usermod or groupadd is missing: sudo apt install passwd"),
        Require("the root has etc/passwd and etc/group",
                lambda t: t.path("/etc/passwd").is_file() and t.path("/etc/group").is_file(),
                "the root holds no etc/passwd or etc/group: --root must be a system's root directory"),
        Require("systemctl found", _have("systemctl"), "systemctl is missing: robotd runs as a systemd service"),
    ]  # fmt: skip
    if board.uses_pigpio:
        steps.append(
            Require(
                "pigpiod.service installed",
                lambda t: unit_installed(t, "pigpiod.service"),
                "pigpiod is not installed: sudo apt install pigpio (Raspberry Pi OS 12 Bookworm or earlier)",
            )
        )
    else:
        steps.append(gpiod_requirement())
    return steps


def gpiod_requirement() -> Require:
    """The gpiod back-end's Python package, importable by the robotd that installs (and will run) the service."""
    found = gpiod_version()
    usable = gpiod_new_enough(found)
    have = f"gpiod {found} is too old (the v1 API)" if found else "the Python package gpiod is not importable"
    return Require(
        f"gpiod {found} importable (>= {'.'.join(map(str, GPIOD_MINIMUM))})",
        lambda _target: usable,
        f"{have} by {sys.executable}: {sys.executable} -m pip install 'robotd[pi5]' (from the checkout) or"
        " pip install 'gpiod>=2.2' (wheels on PyPI); Debian's python3-libgpiod (2.2 on Raspberry Pi OS 13) serves a"
        " venv made with --system-site-packages",
    )


def _source_text(source: Path, relative: str) -> str:
    try:
        return (source / relative).read_text(encoding="utf-8")
    except OSError as error:
        raise InstallError(f"cannot read {source / relative}: {error.strerror or error}") from None


def plan(options: Options, *, removing: bool = False) -> list[Step]:
    """Every step of the installation in order; `removing` includes every removable piece whatever the options."""
    source = options.source
    config_text = _source_text(source, "config/robot.yaml")
    try:
        parse(config_text, str(source / "config/robot.yaml"))
    except ConfigError as error:
        raise InstallError(f"the shipped configuration is invalid: {error.problems[0]}") from None
    pigpio = options.board.uses_pigpio or removing
    unit = render_unit(_source_text(source, "systemd/robotd.service"), options.robotd_path, pigpio=pigpio)
    files = Ownership(0o644)
    private = Ownership(0o640, "root", SERVICE_USER)
    steps = [] if removing else _preconditions(options.board)
    steps += [
        *(Group(group, "the system's device group") for group in DEVICE_GROUPS),
        Group(SERVICE_USER, "it owns the kept configuration"),
        User(SERVICE_USER, HOME, DEVICE_GROUPS, "it owns the kept configuration"),
        Directory(CONFIG_DIR, Ownership(0o750, "root", SERVICE_USER), "your configuration and key"),
        File(CONFIG_PATH, config_text.encode(), private, "config", keep_reason="your configuration"),
        KeyFile(KEY_PATH, private, "the remote controls hold a copy", fresh_key, key_problems),
    ]
    if options.beacon_serial is not None or removing:
        steps.append(File(UDEV_RULE, udev_rule(options.beacon_serial or "").encode(), files, "udev"))
    steps.append(File(UNIT, unit.encode(), files, "units"))
    if pigpio:
        dropin = _source_text(source, "systemd/pigpiod.service.d/robotd.conf")
        steps.append(File(DROP_IN, dropin.encode(), files, "units", prune_parent=True))
    units = ("pigpiod.service", "robotd.service") if pigpio else ("robotd.service",)
    if not removing:
        steps.append(VerifyUnit("robotd.service"))
    steps += [DaemonReload(), UdevReload(), UnitsEnabled(units), UnitsRunning(units)]
    return steps


def _line(verb: str, state: State) -> str:
    return f"  {verb:<10} {state.what}"


def install(steps: list[Step], target: Target, *, dry_run: bool, say: Callable[[str], None]) -> int:
    """Check each step and apply what is not in place (only print it with `dry_run`); returns the number of changes.

    A BLOCKED step stops a real run with InstallError before it changes anything further.
    """
    changes = 0
    for step in steps:
        state = step.check(target)
        if state.kind is Kind.BLOCKED and not dry_run:
            raise InstallError(state.what)
        changes += _carry_out(step, state, step.apply, target, dry_run=dry_run, say=say)
    return changes


def uninstall(steps: list[Step], target: Target, *, dry_run: bool, say: Callable[[str], None]) -> int:
    """Undo the steps, services first and reloads after the files; kept pieces say why. Returns the changes."""
    changes = 0
    order = sorted(enumerate(steps), key=lambda pair: (pair[1].removal_phase, -pair[0]))  # last in, first out
    for _, step in order:
        changes += _carry_out(step, step.check_removal(target), step.remove, target, dry_run=dry_run, say=say)
    return changes


def _carry_out(
    step: Step,
    state: State,
    change: Callable[[Target], None],
    target: Target,
    *,
    dry_run: bool,
    say: Callable[[str], None],
) -> int:
    """Make one step's change when its state asks for one (not with `dry_run`), and say what happened: 1 if changed."""
    changed = 0
    if state.kind is Kind.CHANGE:
        changed = 1
        if not dry_run:
            change(target)
        if step.topic:
            target.changed.add(step.topic)
    elif state.kind is Kind.RECORD:
        target.recorded.append(state.what)
    verb = {Kind.CHANGE: "would" if dry_run else "done"}.get(state.kind, state.kind.value)
    say(_line(verb, state))
    return changed
