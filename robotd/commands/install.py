"""`robotd install` and `robotd uninstall`: set up (or take down) the robot's service, as root on the Pi."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import TextIO

from robotd.tools.host import Board, board_of, read_model, serial_devices, serial_problem
from robotd.tools.install import KEPT_LOGS, Options, find_source, install, plan, uninstall
from robotd.tools.install_steps import InstallError, Target


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `robotd install` and `robotd uninstall`."""
    setup = subparsers.add_parser(
        "install",
        help="set up the robot's service: user, /etc/robotd, teleop key, beacon udev rule, systemd units (as root)",
    )
    _common(setup)
    setup.add_argument("--board", choices=[b.value for b in Board], help="the board (default: from the device tree)")
    setup.add_argument(
        "--beacon-serial", metavar="SERIAL", help="the beacon's USB serial number (default: ask; ls /dev/serial/by-id)"
    )
    setup.add_argument(
        "--robotd", metavar="PATH", help="the robotd program the service runs (default: the one running this)"
    )
    setup.set_defaults(handler=run_install)
    remove = subparsers.add_parser(
        "uninstall", help="stop and remove the robot's service; the configuration, key and logs are kept"
    )
    _common(remove)
    remove.set_defaults(handler=run_uninstall)


def _common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--dry-run", action="store_true", help="print every step, change nothing")
    parser.add_argument(
        "--root", metavar="DIR", default="/", help="install under this directory instead of / (a throw-away root)"
    )
    parser.add_argument(
        "--source", metavar="DIR", help="the robotd checkout with config/ and systemd/ (default: found)"
    )


def _source(args: argparse.Namespace) -> Path:
    candidates = [Path(args.source)] if args.source else [Path(__file__).resolve().parents[2], Path.cwd()]
    found = find_source(candidates)
    if found is None:
        where = " or ".join(str(c) for c in candidates)
        raise InstallError(f"no robotd checkout (config/robot.yaml, systemd/robotd.service) in {where}: use --source")
    return found


def _board(args: argparse.Namespace, root: Path) -> Board:
    if args.board:
        return Board(args.board)
    model = read_model(root)
    board = board_of(model) if model else None
    if board is None:
        seen = f"the device tree says {model!r}" if model else f"{root / 'proc/device-tree/model'} is missing"
        raise InstallError(f"cannot tell which Raspberry Pi this is ({seen}): pass --board pi4 or --board pi5")
    return board


def ask_beacon_serial(root: Path, stdin: TextIO, say: TextIO) -> str | None:
    """Offer the USB serial devices found and read the person's choice; None when there is none or they skip."""
    devices = serial_devices(root)
    if not devices:
        print("no USB serial device in /dev/serial/by-id: plug the beacon in, or pass --beacon-serial", file=say)
        return None
    for number, device in enumerate(devices, 1):
        print(f"  {number}) {device.name} -> {device.target}  (serial {device.serial})", file=say)
    print("Which one is the Marvelmind beacon? number, or Enter to skip the udev rule: ", end="", file=say, flush=True)
    answer = stdin.readline().strip()
    if answer.isdigit() and 1 <= int(answer) <= len(devices):
        return devices[int(answer) - 1].serial
    return None


def _beacon_serial(args: argparse.Namespace, root: Path) -> str | None:
    if args.beacon_serial is not None:
        problem = serial_problem(args.beacon_serial)
        if problem:
            raise InstallError(f"--beacon-serial: {problem}")
        return str(args.beacon_serial)
    serial = ask_beacon_serial(root, sys.stdin, sys.stderr) if sys.stdin.isatty() else None
    if serial is None:
        print("robotd install: no beacon serial number: the udev rule for /dev/marvelmind is not installed", flush=True)
        print("  (rerun with --beacon-serial SERIAL; the serial is the end of its name in /dev/serial/by-id)")
    return serial


def _must_be_root(args: argparse.Namespace, command: str) -> None:
    if not args.dry_run and os.geteuid() != 0:
        raise InstallError(f"run as root: sudo {command} (or --dry-run to see the steps)")


def _robotd_path(args: argparse.Namespace) -> str:
    if args.robotd:
        return str(Path(args.robotd).absolute())
    beside = Path(sys.executable).with_name("robotd")  # the console script of this environment (a venv's bin/)
    return str(beside) if beside.is_file() else "/opt/robotd/.venv/bin/robotd"


def run_install(args: argparse.Namespace) -> int:
    """Install step by step; prints each step and what it did; 1 when a step cannot be applied."""
    root = Path(args.root)
    try:
        _must_be_root(args, "robotd install")
        options = Options(_source(args), _board(args, root), _beacon_serial(args, root), _robotd_path(args))
        print(f"robotd install into {root} ({options.board.value}, from {options.source})", flush=True)
        target = Target(root)
        changes = install(plan(options), target, dry_run=args.dry_run, say=print)
    except InstallError as error:
        print(f"robotd install: {error}", file=sys.stderr)
        return 1
    if args.dry_run:
        print(f"robotd install --dry-run: {changes} change(s) would be made; nothing was written")
    elif changes:
        print(f"robotd install: {changes} change(s) made; check the robot with: robotd doctor --spin")
    else:
        print("robotd install: nothing changed: everything was already in place")
    return 0


def run_uninstall(args: argparse.Namespace) -> int:
    """Stop and remove the service; keeps the configuration, key, user and logs, and says so."""
    root = Path(args.root)
    try:
        _must_be_root(args, "robotd uninstall")
        options = Options(_source(args), Board.PI4, None, _robotd_path(argparse.Namespace(robotd=None)))
        print(f"robotd uninstall from {root}", flush=True)
        changes = uninstall(plan(options, removing=True), Target(root), dry_run=args.dry_run, say=print)
    except InstallError as error:
        print(f"robotd uninstall: {error}", file=sys.stderr)
        return 1
    done = "would be made" if args.dry_run else "made" if changes else "needed: nothing was installed"
    print(
        f"robotd uninstall: {changes} change(s) {done}; kept the configuration and key in /etc/robotd and {KEPT_LOGS}"
    )
    return 0
