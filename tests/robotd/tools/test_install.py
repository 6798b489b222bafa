"""`robotd install` / `robotd uninstall` into a throw-away root, with the real useradd, groupadd and systemctl --root.

The root is seeded as a fresh Raspberry Pi OS would be: /etc/passwd and friends, the pigpio package's unit, and the
device tree's model string. Nothing here touches the running system: the tools get `--prefix ROOT` and
`systemctl --root=ROOT`, and what only a running system can do (start, reload) is recorded, never run.
"""

from __future__ import annotations

import configparser
import io
import os
import shutil
import stat
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

import pytest
from paths import REPO

from drivers.gpiod.lines import gpiod_new_enough
from robotd.cli import main
from robotd.commands.install import ask_beacon_serial
from robotd.daemon.teleop import check_key_file
from robotd.tools.host import Board, board_of, serial_devices, serial_of, serial_problem
from robotd.tools.install import Options, install, plan, render_unit, udev_rule
from robotd.tools.install_steps import Target

PACKAGED_PIGPIOD = (
    "[Unit]\nDescription=Daemon required to control GPIO pins via pigpio\n[Service]\nExecStart=/usr/bin/pigpiod\n"
    "ExecStop=/bin/systemctl kill pigpiod\nType=forking\n[Install]\nWantedBy=multi-user.target\n"
)
SERIAL = "3A8B3C5D3130"

pytestmark = [
    pytest.mark.skipif(os.geteuid() != 0, reason="installing sets owners (chown): run the tests as root"),
    pytest.mark.skipif(
        not all(shutil.which(tool) for tool in ("useradd", "groupadd", "usermod", "systemctl")),
        reason="needs useradd, groupadd, usermod and systemctl",
    ),
]


def fresh_root(tmp_path: Path, model: str = "Raspberry Pi 4 Model B Rev 1.4", pigpio: bool = True) -> Path:
    """A root directory as a freshly flashed Pi has it, as far as robotd install reads and writes."""
    root = tmp_path / "root"
    (root / "etc").mkdir(parents=True)
    (root / "etc/passwd").write_text("root:x:0:0:root:/root:/bin/bash\n")
    (root / "etc/group").write_text("root:x:0:\ndialout:x:20:\n")
    (root / "etc/shadow").write_text("root:*:19000:0:99999:7:::\n")
    (root / "etc/gshadow").write_text("root:*::\ndialout:*::\n")
    (root / "proc/device-tree").mkdir(parents=True)
    (root / "proc/device-tree/model").write_bytes(model.encode() + b"\0")
    if pigpio:
        (root / "lib/systemd/system").mkdir(parents=True)
        (root / "lib/systemd/system/pigpiod.service").write_text(PACKAGED_PIGPIOD)
    return root


def snapshot(root: Path) -> dict[str, tuple[object, ...]]:
    """Every entry under root: content (or link target), mode, owner and modification time."""
    found: dict[str, tuple[object, ...]] = {}
    for path in sorted(root.rglob("*")):
        info = path.lstat()
        if path.is_symlink():
            content: object = os.readlink(path)
        elif path.is_file():
            content = path.read_bytes()
        else:
            content = None
        found[str(path.relative_to(root))] = (content, info.st_mode, info.st_uid, info.st_gid, info.st_mtime_ns)
    return found


def robotd(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str]:
    status = main(list(argv))
    captured = capsys.readouterr()
    return status, captured.out + captured.err


def install_into(root: Path, capsys: pytest.CaptureFixture[str], *extra: str) -> tuple[int, str]:
    return robotd(capsys, "install", "--root", str(root), "--source", str(REPO), "--beacon-serial", SERIAL, *extra)


def group_id(root: Path, name: str) -> int:
    line = next(line for line in (root / "etc/group").read_text().splitlines() if line.startswith(f"{name}:"))
    return int(line.split(":")[2])


def test_install_sets_up_everything_and_a_second_run_changes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = fresh_root(tmp_path)
    status, out = install_into(root, capsys)
    assert status == 0, out
    passwd = (root / "etc/passwd").read_text()
    assert "robotd:x:" in passwd
    assert ":/var/lib/robotd:/usr/sbin/nologin" in passwd
    groups = {line.split(":")[0]: line.split(":")[3] for line in (root / "etc/group").read_text().splitlines()}
    assert groups["gpio"] == "robotd"
    assert groups["dialout"] == "robotd"
    assert "robotd" in groups
    config = root / "etc/robotd/robot.yaml"
    assert config.read_bytes() == (REPO / "config/robot.yaml").read_bytes()
    rule = (root / "etc/udev/rules.d/99-marvelmind.rules").read_text()
    assert f'ATTRS{{serial}}=="{SERIAL}"' in rule
    assert 'SYMLINK+="marvelmind"' in rule
    assert (root / "etc/systemd/system/pigpiod.service.d/robotd.conf").read_bytes() == (
        REPO / "systemd/pigpiod.service.d/robotd.conf"
    ).read_bytes()
    wants = root / "etc/systemd/system/multi-user.target.wants"
    assert sorted(p.name for p in wants.iterdir()) == ["pigpiod.service", "robotd.service"]
    assert "pigpiod.service robotd.service  (under --root the running system is not touched)" in out  # recorded
    assert (root / "etc/robotd").stat().st_gid == group_id(root, "robotd")

    before = snapshot(root)
    status, out = install_into(root, capsys)
    assert status == 0, out
    assert "nothing changed" in out
    assert "done" not in out
    assert snapshot(root) == before  # not even rewritten with the same bytes


def test_the_key_is_fresh_private_and_accepted_by_the_daemons_own_check(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    first, second = fresh_root(tmp_path / "a"), fresh_root(tmp_path / "b")
    install_into(first, capsys)
    install_into(second, capsys)
    key = first / "etc/robotd/teleop.key"
    info = key.stat()
    assert stat.S_IMODE(info.st_mode) == 0o640
    assert (info.st_uid, info.st_gid) == (0, group_id(first, "robotd"))
    assert check_key_file(key) == []
    assert key.read_bytes() != (second / "etc/robotd/teleop.key").read_bytes()


def test_a_key_made_public_is_made_private_again_and_never_replaced(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = fresh_root(tmp_path)
    install_into(root, capsys)
    key = root / "etc/robotd/teleop.key"
    content = key.read_bytes()
    key.chmod(0o644)
    status, out = install_into(root, capsys)
    assert status == 0
    assert "mode 0644 -> 0640" in out
    assert stat.S_IMODE(key.stat().st_mode) == 0o640
    assert key.read_bytes() == content


def test_an_edited_configuration_is_kept(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    root = fresh_root(tmp_path)
    install_into(root, capsys)
    config = root / "etc/robotd/robot.yaml"
    edited = config.read_text().replace("ppr: 1700", "ppr: 1024")
    config.write_text(edited)
    status, out = install_into(root, capsys)
    assert status == 0
    assert "edited: kept as it is" in out
    assert "nothing changed" in out
    assert config.read_text() == edited


def test_a_key_file_holding_no_key_stops_the_installation(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    root = fresh_root(tmp_path)
    install_into(root, capsys)
    key = root / "etc/robotd/teleop.key"
    key.write_bytes(b"short\n")
    status, out = install_into(root, capsys)
    assert status == 1
    assert "never replaces a key" in out
    assert key.read_bytes() == b"short\n"


def test_dry_run_prints_every_step_and_writes_nothing(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    root = fresh_root(tmp_path)
    before = snapshot(root)
    status, out = install_into(root, capsys, "--dry-run")
    assert status == 0, out
    assert snapshot(root) == before
    for step in ("create system group robotd", "create system user robotd", "install /etc/robotd/robot.yaml",
                 "create a fresh key /etc/robotd/teleop.key", "install /etc/udev/rules.d/99-marvelmind.rules",
                 "install /etc/systemd/system/robotd.service", "enable pigpiod.service robotd.service"):  # fmt: skip
        assert f"would      {step}" in out
    assert "nothing was written" in out


def test_a_missing_pigpio_package_stops_before_anything_changes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = fresh_root(tmp_path, pigpio=False)
    before = snapshot(root)
    status, out = install_into(root, capsys)
    assert status == 1
    assert "sudo apt install pigpio" in out
    assert snapshot(root) == before


def test_a_pi5_gets_no_pigpiod(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    root = fresh_root(tmp_path, model="Raspberry Pi 5 Model B Rev 1.0", pigpio=False)
    status, out = install_into(root, capsys)
    assert status == 0, out
    assert "(pi5," in out
    unit = (root / "etc/systemd/system/robotd.service").read_text()
    assert "pigpiod.service" not in unit
    assert not (root / "etc/systemd/system/pigpiod.service.d").exists()
    wants = root / "etc/systemd/system/multi-user.target.wants"
    assert [p.name for p in wants.iterdir()] == ["robotd.service"]


def test_an_unknown_board_must_be_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    root = fresh_root(tmp_path, model="Generic x86 PC")
    status, out = install_into(root, capsys)
    assert status == 1
    assert "--board pi4 or --board pi5" in out
    status, out = install_into(root, capsys, "--board", "pi4")
    assert status == 0, out


def test_without_a_beacon_serial_the_rule_is_left_out_and_said_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = fresh_root(tmp_path)
    status, out = robotd(capsys, "install", "--root", str(root), "--source", str(REPO))
    assert status == 0, out
    assert "udev rule for /dev/marvelmind is not installed" in out
    assert not (root / "etc/udev/rules.d/99-marvelmind.rules").exists()


def test_a_serial_that_could_break_the_rule_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    root = fresh_root(tmp_path)
    status, out = robotd(capsys, "install", "--root", str(root), "--source", str(REPO), "--beacon-serial", 'x", RUN+="')
    assert status == 1
    assert "not a USB serial number" in out


def test_uninstall_removes_the_service_and_keeps_configuration_key_and_logs(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = fresh_root(tmp_path)
    install_into(root, capsys)
    (root / "var/lib/robotd").mkdir(parents=True)
    (root / "var/lib/robotd/run.jsonl").write_text("{}\n")
    key = (root / "etc/robotd/teleop.key").read_bytes()
    status, out = robotd(capsys, "uninstall", "--root", str(root), "--source", str(REPO))
    assert status == 0, out
    for gone in ("etc/systemd/system/robotd.service", "etc/systemd/system/pigpiod.service.d",
                 "etc/udev/rules.d/99-marvelmind.rules", "etc/systemd/system/multi-user.target.wants/robotd.service",
                 "etc/systemd/system/multi-user.target.wants/pigpiod.service"):  # fmt: skip
        assert not (root / gone).exists(), gone
    assert (root / "etc/robotd/robot.yaml").read_bytes() == (REPO / "config/robot.yaml").read_bytes()
    assert (root / "etc/robotd/teleop.key").read_bytes() == key
    assert (root / "var/lib/robotd/run.jsonl").exists()
    assert "kept       /etc/robotd/robot.yaml" in out
    assert "kept the configuration and key in /etc/robotd and the logs" in out
    assert "systemctl stop robotd.service pigpiod.service" in out  # recorded for the running system

    before = snapshot(root)
    status, out = robotd(capsys, "uninstall", "--root", str(root), "--source", str(REPO))
    assert status == 0
    assert "0 change(s)" in out
    assert snapshot(root) == before


def test_the_installed_unit_passes_the_unit_checks(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    root = fresh_root(tmp_path)
    status, out = install_into(root, capsys)
    assert status == 0, out
    assert "robotd.service passes systemd-analyze verify" in out
    installed = root / "etc/systemd/system/robotd.service"
    units = ":".join(str(root / d) for d in ("etc/systemd/system", "lib/systemd/system"))
    verified = subprocess.run(
        ["systemd-analyze", "verify", str(installed)],
        capture_output=True,
        text=True,
        env=os.environ | {"SYSTEMD_UNIT_PATH": f"{units}:", "SYSTEMD_LOG_COLOR": "0"},
        timeout=60,
        check=False,
    )
    assert verified.stderr == ""
    assert verified.returncode == 0
    unit = configparser.ConfigParser(strict=False, interpolation=None)
    unit.optionxform = str  # type: ignore[assignment,method-assign]  # systemd keys are case-sensitive
    unit.read_string(installed.read_text())
    service = unit["Service"]
    assert service["Type"] == "notify"
    assert set(service["SupplementaryGroups"].split()) == {"gpio", "dialout"}
    assert service["User"] == "robotd"
    program = service["ExecStart"].split()[0]
    assert program == str(Path(sys.executable).with_name("robotd"))  # the robotd that ran the installation
    assert os.access(program, os.X_OK)
    assert service["ExecStopPost"].split()[:2] == [program, "stop-motors"]


class LiveTarget(Target):
    """The running system, as far as the steps can tell, with its files kept under a temporary directory."""

    @property
    def live(self) -> bool:
        return True


def test_on_the_running_system_it_reloads_enables_and_starts(tmp_path: Path) -> None:
    root = fresh_root(tmp_path)
    (root / "run/systemd/system").mkdir(parents=True)
    (root / "run/udev").mkdir(parents=True)
    ran: list[list[str]] = []
    enabled: set[str] = set()

    def systemd(argv: Sequence[str]) -> subprocess.CompletedProcess[str]:
        """useradd and groupadd for real (under the root), systemctl and udevadm pretended."""
        argv = list(argv)
        ran.append(argv)
        if argv[0] in ("useradd", "groupadd", "usermod"):
            return subprocess.run(
                [*argv[:1], "--prefix", str(root), *argv[1:]], capture_output=True, text=True, check=False
            )
        if argv[:2] == ["systemctl", "enable"]:
            enabled.update(argv[2:])
        if argv[:2] == ["systemctl", "is-enabled"]:
            return subprocess.CompletedProcess(argv, 0, "enabled\n" if argv[2] in enabled else "disabled\n", "")
        if argv[:2] == ["systemctl", "is-active"]:
            return subprocess.CompletedProcess(argv, 3, "inactive\n", "")
        return subprocess.CompletedProcess(argv, 0, "", "")

    options = Options(REPO, Board.PI4, SERIAL, str(Path(sys.executable).with_name("robotd")))
    target = LiveTarget(root, run=systemd)
    install(plan(options), target, dry_run=False, say=lambda _line: None)
    commands = [" ".join(argv) for argv in ran if argv[0] != "env"]
    assert "groupadd --system robotd" in commands  # no --prefix: this is the running system
    assert "systemctl daemon-reload" in commands
    assert "udevadm control --reload" in commands
    assert "udevadm trigger --subsystem-match=tty --action=add" in commands
    assert "systemctl enable pigpiod.service robotd.service" in commands
    assert commands[-1] == "systemctl restart pigpiod.service robotd.service"  # the configuration is new
    assert commands.index("systemctl daemon-reload") < commands.index("systemctl enable pigpiod.service robotd.service")
    assert target.recorded == []


def test_board_models() -> None:
    assert board_of("Raspberry Pi 4 Model B Rev 1.4") is Board.PI4
    assert board_of("Raspberry Pi 3 Model B Plus Rev 1.3") is Board.PI4
    assert board_of("Raspberry Pi 5 Model B Rev 1.0") is Board.PI5
    assert board_of("Raspberry Pi Compute Module 5 Rev 1.0") is Board.PI5
    assert board_of("Raspberry Pi 500 Rev 1.0") is Board.PI5
    assert board_of("Generic x86 PC") is None


def test_serial_numbers_from_by_id_names(tmp_path: Path) -> None:
    assert serial_of("usb-STMicroelectronics_STM32_Virtual_ComPort_3A8B3C5D3130-if00") == "3A8B3C5D3130"
    assert serial_of("usb-Marvelmind_Robotics_Hedgehog_0123-if01-port0") == "0123"
    assert serial_of("pci-0000:00:14.0-usb-0:1:1.0") is None
    by_id = tmp_path / "dev/serial/by-id"
    by_id.mkdir(parents=True)
    (by_id / "usb-STMicroelectronics_STM32_Virtual_ComPort_3A8B3C5D3130-if00").symlink_to("../../ttyACM0")
    [device] = serial_devices(tmp_path)
    assert (device.serial, device.target) == ("3A8B3C5D3130", "../../ttyACM0")
    assert serial_problem("3A8B3C5D3130") is None
    assert serial_problem('a" RUN+="/bin/sh') is not None


def test_the_unit_for_a_board_without_pigpio_drops_only_pigpiod() -> None:
    shipped = (REPO / "systemd/robotd.service").read_text()
    rendered = render_unit(shipped, "/usr/local/bin/robotd", pigpio=False)
    assert "pigpiod" not in rendered.split("[Service]")[0]
    assert "After=network-online.target" in rendered
    assert "ExecStart=/usr/local/bin/robotd run --config /etc/robotd/robot.yaml" in rendered
    kept = [line for line in shipped.splitlines() if "pigpiod" not in line and "/opt/robotd/.venv" not in line]
    assert all(line in rendered.splitlines() for line in kept)


def test_the_udev_rule_matches_the_beacon_by_serial() -> None:
    rule = udev_rule(SERIAL)
    match = rule.splitlines()[1]
    assert match.startswith('SUBSYSTEM=="tty", ATTRS{idVendor}=="0483"')
    assert f'ATTRS{{serial}}=="{SERIAL}"' in match
    assert 'GROUP="dialout", MODE="0660"' in match


def test_the_beacon_is_picked_from_the_serial_devices_by_id(tmp_path: Path) -> None:
    by_id = tmp_path / "dev/serial/by-id"
    by_id.mkdir(parents=True)
    (by_id / "usb-FTDI_FT232R_USB_UART_A50285BI-if00-port0").symlink_to("../../ttyUSB0")
    (by_id / f"usb-STMicroelectronics_STM32_Virtual_ComPort_{SERIAL}-if00").symlink_to("../../ttyACM0")
    shown = io.StringIO()
    assert ask_beacon_serial(tmp_path, io.StringIO("2\n"), shown) == SERIAL
    assert f"2) usb-STMicroelectronics_STM32_Virtual_ComPort_{SERIAL}-if00 -> ../../ttyACM0" in shown.getvalue()
    assert ask_beacon_serial(tmp_path, io.StringIO("\n"), io.StringIO()) is None  # skipped: no rule
    assert ask_beacon_serial(tmp_path / "none", io.StringIO("1\n"), io.StringIO()) is None


def test_a_pi5_without_a_usable_gpiod_package_stops_before_anything_changes_and_says_how_to_get_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    root = fresh_root(tmp_path, model="Raspberry Pi 5 Model B Rev 1.0", pigpio=False)
    before = snapshot(root)
    monkeypatch.setattr("robotd.tools.install.gpiod_version", lambda: None)
    status, out = install_into(root, capsys)
    assert status == 1
    assert "the Python package gpiod is not importable" in out
    assert "-m pip install 'robotd[pi5]'" in out
    assert snapshot(root) == before
    monkeypatch.setattr("robotd.tools.install.gpiod_version", lambda: "1.6.3")  # Bookworm's, the v1 API
    status, out = install_into(root, capsys)
    assert (status, "gpiod 1.6.3 is too old (the v1 API)" in out) == (1, True)
    monkeypatch.undo()
    status, out = install_into(root, capsys)  # the real one, installed with the test extra
    assert status == 0, out
    assert "gpiod 2." in out


@pytest.mark.parametrize(
    ("version", "usable"),
    [("2.2.1", True), ("2.5.0", True), ("2.10", True), ("3.0", True), ("2.1.3", False), ("1.6.3", False),
     ("2.2.0rc1", True), ("", False), (None, False)],
)  # fmt: skip
def test_gpiod_versions_from_2_2_on_are_usable(version: str | None, usable: bool) -> None:
    assert gpiod_new_enough(version) is usable
