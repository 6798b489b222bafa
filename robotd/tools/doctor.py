"""`robotd doctor`: the checklist a person runs on a freshly wired robot, each line PASS, FAIL with the fix, or SKIP
with the reason.

Order: the configuration, the GPIO back-end (the configuration's, unless named), the pins, the beacon, the teleop
key, the service, the clock, and with --spin each wheel (robotd.tools.doctor_spin). A check that needs what an
earlier one found missing is skipped and says so. The findings are printed as they come: a person watches the
robot while it runs.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from robotd.config.gpio import resolve_backend
from robotd.config.model import RobotdConfig, load
from robotd.config.schema import ConfigError
from robotd.tools.checklist import Finding, failed, passed, skipped
from robotd.tools.doctor_beacon import BeaconSample, beacon_findings, find_device, listen_daemon, listen_serial
from robotd.tools.doctor_host import clock_finding, key_finding, unit_finding
from robotd.tools.doctor_pins import holder_findings, pin_findings, pins_in_use
from robotd.tools.doctor_spin import Ask, SpinPlan, diagnose, spin_wheels
from robotd.tools.gpio_backend import BackendUnavailableError, GpioBackend, backends
from robotd.tools.install_steps import Runner, run_command


@dataclass(frozen=True, slots=True)
class DoctorOptions:
    """What to check and how."""

    config_path: str
    backend: str | None = None  # None: the configuration's gpio.backend (auto: by the board)
    beacon_s: float = 3.0  # how long to listen to the beacon
    spin: SpinPlan | None = None  # None: leave the wheels alone
    ask: Ask | None = None  # asks the person which way each wheel turned; None: nobody watches


@dataclass(frozen=True, slots=True)
class Host:
    """The host's side of the checks, replaced in tests."""

    run: Runner = run_command
    dev: Path = Path("/dev")
    systemd_dir: Path = Path("/run/systemd/system")
    backends: dict[str, GpioBackend] = field(default_factory=backends)


Report = Callable[[Finding], None]


async def examine(options: DoctorOptions, host: Host, report: Report, note: Callable[[str], None]) -> list[Finding]:
    """Run every check, reporting each finding as it comes; returns them all."""
    findings: list[Finding] = []

    def add(*new: Finding) -> None:
        for finding in new:
            findings.append(finding)
            report(finding)

    try:
        config = load(options.config_path)
    except ConfigError as error:
        add(
            *(
                failed("configuration", problem, "correct the file (robotd config-reference)")
                for problem in error.problems
            )
        )
        return findings
    add(passed("configuration", f"{options.config_path} is valid"))
    backend = host.backends[options.backend or resolve_backend(config.gpio)]
    try:
        add(passed("GPIO back-end", f"{backend.name}: {await asyncio.to_thread(backend.reach, config)}"))
        reachable = True
    except BackendUnavailableError as error:
        add(failed("GPIO back-end", f"{backend.name}: {error.detail}", error.fix))
        reachable = False
    add(*await _pins(config, backend, host, reachable))
    daemon_running, sample = await _listen(config, options.beacon_s)
    add(*beacon_findings(config.marvelmind, find_device(config.marvelmind.device), sample))
    add(key_finding(config), unit_finding(options.config_path, host.run, host.systemd_dir), clock_finding(host.run))
    if options.spin is not None:
        if not reachable:
            add(skipped("spin", "the GPIO back-end is not reachable"))
        else:
            if daemon_running:
                note("robotd is running: nobody may drive it with teleop while the wheels spin")
            add(*await _spin(config, backend, options.spin, options.ask, note))
    return findings


async def _pins(config: RobotdConfig, backend: GpioBackend, host: Host, reachable: bool) -> list[Finding]:
    modes, unknown = None, "the GPIO back-end is not reachable, so the pins' present functions are unknown"
    pins = [pin for _, pin in pins_in_use(config)]
    if reachable and backend.pin_modes is None:
        unknown = f"the {backend.name} back-end cannot read pin functions (pinctrl get {','.join(map(str, pins))} can)"
    elif reachable and backend.pin_modes is not None:
        try:
            modes = await asyncio.to_thread(backend.pin_modes, config, pins)
        except BackendUnavailableError:
            modes = None
    found = pin_findings(config, modes, host.dev, backend.pwm_pins, unknown=unknown)
    if reachable and backend.pin_holders is not None:
        try:
            found += holder_findings(config, await asyncio.to_thread(backend.pin_holders, config, pins))
        except BackendUnavailableError as error:
            found.append(failed("pins free", error.detail, error.fix))
    return found


async def _listen(config: RobotdConfig, seconds: float) -> tuple[bool, BeaconSample | str]:
    """(robotd running?, what was heard or why nothing could be): the daemon's status when it runs, else the port."""
    socket_path = config.pose_socket.path
    timeout = seconds + 3.0 / config.pose_socket.status_rate_hz
    try:
        return True, await asyncio.to_thread(listen_daemon, socket_path, seconds, timeout)
    except (FileNotFoundError, ConnectionRefusedError):
        pass  # robotd is not running: the port is free to read
    except PermissionError:
        return True, f"robotd's pose socket {socket_path} is not yours to read"
    except (OSError, ValueError) as error:
        return True, f"robotd's status could not be read from {socket_path}: {error}"
    device = find_device(config.marvelmind.device)
    if device is None:
        return False, "no device"
    try:
        return False, await asyncio.to_thread(listen_serial, device, config.marvelmind, seconds)
    except OSError as error:
        return False, f"cannot open {device}: {error.strerror or error}"


async def _spin(
    config: RobotdConfig, backend: GpioBackend, plan: SpinPlan, ask: Ask | None, note: Callable[[str], None]
) -> list[Finding]:
    note(
        f"spinning each wheel in turn at duty {plan.duty:g} for {plan.ramp_s + plan.measure_s:g} s:"
        " the wheels must be off the ground"
    )
    try:
        drive = await asyncio.to_thread(backend.open_drive, config)
    except BackendUnavailableError as error:
        return [failed("spin", error.detail, error.fix)]
    try:
        async with backend.open_counts(config) as counts:
            runs = await spin_wheels(drive, counts, plan, ask=ask)
    except BackendUnavailableError as error:
        return [failed("spin", error.detail, error.fix)]
    finally:
        await asyncio.to_thread(drive.close)
    return diagnose(runs, config, plan)
