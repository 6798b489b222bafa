"""The doctor's checks of the host: the teleop key, the systemd unit, the clock.

Each asks a real tool (systemctl, timedatectl, chronyc) through a runner the tests replace, and skips with the
reason when the tool is missing or systemd is not running (a container, the virtual robot on a laptop).
"""

from __future__ import annotations

from pathlib import Path

from robotd.config.model import RobotdConfig
from robotd.daemon.teleop import check_key_file
from robotd.tools.checklist import Finding, failed, passed, skipped
from robotd.tools.install_steps import Runner

SERVICE = "robotd.service"
SERVICE_CONFIG = "/etc/robotd/robot.yaml"
CLOCK_MATTERS = "teleop drops commands whose sender clock is off by more than teleop.max_clock_offset_s"


def key_finding(config: RobotdConfig) -> Finding:
    """The teleop key file is there, valid, and private (robotd's own start-up check)."""
    teleop = config.teleop
    if not teleop.key_file:
        return skipped("teleop key", "none configured: teleop.allow_unauthenticated on loopback (simulation only)")
    problems = check_key_file(teleop.key_file)
    if problems:
        detail, _, command = problems[0].removeprefix("teleop.key_file: ").partition(": run ")
        if command:
            fix = command.strip("`")
        elif "No such file" in detail:
            fix = "sudo robotd install makes a fresh one"
        elif "Permission denied" in detail:
            fix = "run the doctor as root (sudo), as the key is private"
        else:
            fix = f"write a fresh key: head -c 32 /dev/urandom | base64 | sudo tee {teleop.key_file}"
        return failed("teleop key", detail, fix)
    return passed("teleop key", f"{teleop.key_file}: a valid key, readable by its owner and robotd's group only")


def _tool(run: Runner, *argv: str) -> tuple[int, str] | None:
    """(exit status, stdout stripped), or None when the tool is not installed (exit 127)."""
    result = run(argv)
    return None if result.returncode == 127 else (result.returncode, result.stdout.strip())


def unit_finding(config_path: str, run: Runner, systemd_dir: Path = Path("/run/systemd/system")) -> Finding:
    """robotd.service is active and has not been restarting, when systemd runs and the service runs this config."""
    if not systemd_dir.is_dir():
        return skipped("service", "systemd is not running here (a container, or the virtual robot)")
    if Path(config_path).absolute() != Path(SERVICE_CONFIG):
        return skipped("service", f"robotd.service runs {SERVICE_CONFIG}, not {config_path}")
    state = _tool(run, "systemctl", "is-active", SERVICE)
    restarts = _tool(run, "systemctl", "show", SERVICE, "--property=NRestarts", "--value")
    enabled = _tool(run, "systemctl", "is-enabled", SERVICE)
    if state is None or restarts is None or enabled is None:
        return skipped("service", "systemctl is not installed")
    if enabled[1] in ("", "not-found") or "No such file" in enabled[1]:
        return failed("service", f"{SERVICE} is not installed", "sudo robotd install")
    if state[1] != "active":
        return failed("service", f"{SERVICE} is {state[1] or 'unknown'}", "journalctl -u robotd -b -n 50 says why")
    count = int(restarts[1]) if restarts[1].isdigit() else 0
    if count:
        return failed(
            "service", f"{SERVICE} is active but systemd restarted it {count} times", "journalctl -u robotd -b"
        )
    boot = "" if enabled[1] == "enabled" else f", but {enabled[1]} at boot (sudo systemctl enable robotd)"
    return passed("service", f"{SERVICE} active, never restarted{boot}")


def clock_finding(run: Runner) -> Finding:
    """The system clock is synchronised (timedatectl, else chrony)."""
    timedate = _tool(run, "timedatectl", "show", "--property=NTPSynchronized", "--value")
    if timedate is not None and timedate[0] == 0 and timedate[1] in ("yes", "no"):
        if timedate[1] == "yes":
            return passed("clock", "synchronised (timedatectl)")
        return failed("clock", f"not synchronised (timedatectl): {CLOCK_MATTERS}", "sudo timedatectl set-ntp true")
    chrony = _tool(run, "chronyc", "-n", "tracking")
    if chrony is not None and chrony[0] == 0:
        leap = next((line.split(":", 1)[1].strip() for line in chrony[1].splitlines() if "Leap status" in line), "")
        if leap == "Normal":
            return passed("clock", "synchronised (chronyc tracking)")
        return failed(
            "clock", f"chrony: leap status {leap or 'unknown'}: {CLOCK_MATTERS}", "chronyc sources -v shows why"
        )
    return skipped("clock", "neither timedatectl (needs systemd running) nor chronyc could tell")
