"""The systemd units pass `systemd-analyze verify` with nothing on stderr (a missing verifier is a failure)."""

from __future__ import annotations

import configparser
import os
import shutil
import subprocess
import sys
from pathlib import Path

from paths import REPO as ROOT

UNITS = ROOT / "systemd"
INSTALLED_ROBOTD = "/opt/robotd/.venv/bin/robotd"
INSTALLED_PIGPIOD = "/usr/bin/pigpiod"
# What Raspberry Pi OS's pigpio package ships, so the drop-in is verified against a real base unit.
PACKAGED_PIGPIOD = """[Unit]
Description=Daemon required to control GPIO pins via pigpio
[Service]
ExecStart=/usr/bin/pigpiod
ExecStop=/bin/systemctl kill pigpiod
Type=forking
[Install]
WantedBy=multi-user.target
"""


def verifier() -> str:
    found = shutil.which("systemd-analyze") or "/usr/bin/systemd-analyze"
    assert os.access(found, os.X_OK), "systemd-analyze is needed to check the units"
    return found


def here(text: str) -> str:
    """A unit's text with the Pi's install paths replaced by binaries that exist on this machine."""
    robotd = str(Path(sys.executable).with_name("robotd"))
    pigpiod = shutil.which("pigpiod") or "/bin/true"
    return text.replace(INSTALLED_ROBOTD, robotd).replace(INSTALLED_PIGPIOD, pigpiod)


def install(tmp_path: Path) -> Path:
    units = tmp_path / "units"
    (units / "pigpiod.service.d").mkdir(parents=True)
    (units / "robotd.service").write_text(here((UNITS / "robotd.service").read_text()))
    (units / "pigpiod.service").write_text(here(PACKAGED_PIGPIOD))
    dropin = (UNITS / "pigpiod.service.d" / "robotd.conf").read_text()
    (units / "pigpiod.service.d" / "robotd.conf").write_text(here(dropin))
    return units


def verify(units: Path, *names: str) -> subprocess.CompletedProcess[str]:
    env = os.environ | {"SYSTEMD_UNIT_PATH": f"{units}:", "SYSTEMD_LOG_COLOR": "0"}
    return subprocess.run(
        [verifier(), "verify", *(str(units / name) for name in names)],
        capture_output=True,
        text=True,
        env=env,
        timeout=60,
        check=False,
    )


def test_units_verify_cleanly(tmp_path: Path) -> None:
    units = install(tmp_path)
    result = verify(units, "robotd.service", "pigpiod.service")
    assert result.stderr == ""
    assert result.returncode == 0


def test_the_verifier_does_catch_a_broken_unit(tmp_path: Path) -> None:
    units = install(tmp_path)
    robotd = units / "robotd.service"
    robotd.write_text(robotd.read_text().replace("WatchdogSec=", "WatchdogSecs="))
    assert "Unknown key" in verify(units, "robotd.service").stderr


def test_the_unit_says_what_the_issue_asks() -> None:
    unit = configparser.ConfigParser(strict=False, interpolation=None)
    unit.optionxform = str  # type: ignore[assignment,method-assign]  # systemd keys are case-sensitive
    text = (UNITS / "robotd.service").read_text()
    unit.read_string(text)
    service = unit["Service"]
    assert service["Type"] == "notify"
    assert service["Restart"] == "on-failure"
    assert service["RuntimeDirectory"] == "robotd"
    assert set(service["SupplementaryGroups"].split()) == {"gpio", "dialout"}
    assert service["ExecStopPost"].split()[1] == "stop-motors"
    assert "WatchdogSec" in service
    assert unit["Unit"]["Requires"] == "pigpiod.service"
    assert "pigpiod.service" in unit["Unit"]["After"].split()
    assert "PrivateDevices=yes" not in text  # it would hide the tty and GPIO devices


def test_pigpiod_listens_on_localhost_only() -> None:
    dropin = (UNITS / "pigpiod.service.d" / "robotd.conf").read_text().splitlines()
    starts = [line.split("=", 1)[1] for line in dropin if line.startswith("ExecStart=")]
    assert starts[0] == ""  # clears the packaged command
    assert "-l" in starts[1].split()
