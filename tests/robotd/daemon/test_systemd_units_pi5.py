"""The unit as `robotd install` renders it for a Raspberry Pi 5: no pigpiod, the RP1's PWM writable, and it verifies."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

from paths import REPO

from robotd.tools.install import render_unit

UNIT = (REPO / "systemd" / "robotd.service").read_text()
RP1_PWM_DEVICE_PATH = "/sys/devices/platform/axi/1000120000.pcie/1f00098000.pwm"


def pi5_unit() -> str:
    return render_unit(UNIT, str(Path(sys.executable).with_name("robotd")), pigpio=False)


def test_the_pi5_unit_needs_no_pigpiod_and_keeps_the_rp1_pwm_writable() -> None:
    unit = pi5_unit()
    assert "pigpiod.service" not in unit
    lines = unit.splitlines()
    assert "ProtectKernelTunables=yes" in lines  # the rest of /sys stays read-only
    assert f"ReadWritePaths=-{RP1_PWM_DEVICE_PATH}" in lines
    assert any(line.startswith("DeviceAllow=char-gpiochip") for line in lines)  # the encoder and direction lines
    assert any(line.startswith("ExecStopPost=") and " stop-motors " in line for line in lines)


def test_the_pi5_unit_verifies_cleanly(tmp_path: Path) -> None:
    (tmp_path / "robotd.service").write_text(pi5_unit())
    verifier = shutil.which("systemd-analyze") or "/usr/bin/systemd-analyze"
    result = subprocess.run(
        [verifier, "verify", str(tmp_path / "robotd.service")],
        capture_output=True,
        text=True,
        env=os.environ | {"SYSTEMD_UNIT_PATH": f"{tmp_path}:", "SYSTEMD_LOG_COLOR": "0"},
        timeout=60,
        check=False,
    )
    assert (result.returncode, result.stderr) == (0, "")
