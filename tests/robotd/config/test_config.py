"""Configuration: every validation rule with a failing and a passing example, and the CLI's exit status 78."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from paths import REPO

from robotd.cli import EX_CONFIG, main
from robotd.config.model import RobotdConfig, config_reference, load, parse
from robotd.config.schema import ConfigError
from robotd.readme import current, import_map


def problems_of(text: str) -> list[str]:
    """The problems that parsing `text` reports (empty when it is valid)."""
    try:
        parse(text)
    except ConfigError as error:
        return error.problems
    return []


# (description, a valid YAML snippet, an invalid one, the start of the expected problem line)
RULES = [
    (
        "positive",
        "teleop: {deadman_timeout_s: 0.2}",
        "teleop: {deadman_timeout_s: -1}",
        "teleop.deadman_timeout_s: must be > 0 and at most 5, got -1",
    ),
    (
        "positive rejects zero",
        "robot: {wheel_radius_m: 0.05}",
        "robot: {wheel_radius_m: 0}",
        "robot.wheel_radius_m: must be > 0, got 0",
    ),
    (
        "non-negative",
        "ekf: {odom_along_sigma_m: 0}",
        "ekf: {odom_along_sigma_m: -0.5}",
        "ekf.odom_along_sigma_m: must be >= 0, got -0.5",
    ),
    ("in range", "control: {rate_hz: 100}", "control: {rate_hz: 5000}", "control.rate_hz: must be between"),
    (
        "gpio pin",
        "encoders: {wheels: {front_left: {a: 7}}}",
        "encoders: {wheels: {front_left: {a: 40}}}",
        "encoders.wheels.front_left.a: must be a BCM GPIO number",
    ),
    ("port", "pigpiod: {port: 8889}", "pigpiod: {port: 70000}", "pigpiod.port: must be a port"),
    (
        "sign",
        "motors: {wheels: {rear_right: {sign: -1}}}",
        "motors: {wheels: {rear_right: {sign: 2}}}",
        "motors.wheels.rear_right.sign: must be 1 or -1, got 2",
    ),
    (
        "each element",
        "ekf: {initial_sigma: [0.5, 0.5, 0.2]}",
        "ekf: {initial_sigma: [0.5, -0.5, 0.2]}",
        "ekf.initial_sigma: element 1 must be > 0",
    ),
    ("literal", "encoders: {decoding: x2}", "encoders: {decoding: x3}", "encoders.decoding: expected 'x1' or"),
    (
        "address auto",
        "marvelmind: {hedgehog_address: auto}",
        "marvelmind: {hedgehog_address: any}",
        "marvelmind.hedgehog_address: expected",
    ),
    (
        "address range",
        "marvelmind: {hedgehog_address: 12}",
        "marvelmind: {hedgehog_address: 300}",
        "marvelmind: hedgehog_address must be between 0 and 255",
    ),
    (
        "octal mode",
        "pose_socket: {mode: '0640'}",
        "pose_socket: {mode: '0999'}",
        "pose_socket.mode: must be octal permissions",
    ),
    (
        "numeric list element",
        "ekf: {initial_pose: [1, 2, 0.5]}",
        "ekf: {initial_pose: [1, two, 0.5]}",
        "ekf.initial_pose[1]: expected a number, got string 'two'",
    ),
    (
        "no key with a key file",
        "teleop: {allow_unauthenticated: true, key_file: ''}",
        "teleop: {allow_unauthenticated: true}",
        "teleop.allow_unauthenticated: true together with teleop.key_file (/etc/robotd/teleop.key)",
    ),
    (
        "no key off loopback",
        "teleop: {allow_unauthenticated: true, key_file: '', bind: '::1'}",
        "teleop: {allow_unauthenticated: true, key_file: '', bind: 10.0.0.5}",
        "teleop.bind: teleop without a key (teleop.allow_unauthenticated) must listen on loopback",
    ),
    ("bind literal", "teleop: {bind: '::'}", "teleop: {bind: 10.0.0.256}", "teleop.bind: must be an IP address"),
    (
        "pigpiod host",
        "pigpiod: {host: pi-4.lan}",
        "pigpiod: {host: 'pi 4'}",
        "pigpiod.host: must be a valid IP address or a host name",
    ),
    (
        "number type",
        "teleop: {max_vx_mps: 1}",
        "teleop: {max_vx_mps: fast}",
        "teleop.max_vx_mps: expected a number, got string 'fast'",
    ),
    (
        "bool is no number",
        "teleop: {max_vx_mps: 0.4}",
        "teleop: {max_vx_mps: true}",
        "teleop.max_vx_mps: expected a number, got boolean True",
    ),
    ("finite number", "robot: {lx_m: 0.2}", "robot: {lx_m: .inf}", "robot.lx_m: must be a finite number"),
    ("integer type", "encoders: {ppr: 500}", "encoders: {ppr: 500.5}", "encoders.ppr: expected a integer"),
    (
        "boolean type",
        "teleop: {allow_unauthenticated: true, key_file: ''}",
        "ekf: {gating: 'yes'}",
        "ekf.gating: expected a true or false",
    ),
    (
        "string type",
        "marvelmind: {device: /dev/ttyACM0}",
        "marvelmind: {device: 5}",
        "marvelmind.device: expected a string, got integer 5",
    ),
    (
        "list length",
        "robot: {ips_offset_m: [0.1, 0.0]}",
        "robot: {ips_offset_m: [0.1]}",
        "robot.ips_offset_m: expected a list of 2 numbers, got 1 elements",
    ),
    (
        "list type",
        "robot: {ips_offset_m: [0.1, 0.0]}",
        "robot: {ips_offset_m: 0.1}",
        "robot.ips_offset_m: expected a list of 2 numbers",
    ),
    ("section is a mapping", "teleop: {}", "teleop: 5", "teleop: expected a mapping, got integer 5"),
    ("null value", "teleop: {port: 47801}", "teleop: {port: null}", "teleop.port: expected a integer, got nothing"),
    (
        "unknown key, near match",
        "teleop: {deadman_timeout_s: 1}",
        "teleop: {deadman_timout_s: 1}",
        "teleop.deadman_timout_s: unknown key (did you mean 'deadman_timeout_s'?)",
    ),
    ("unknown key, no match", "robot: {}", "robot: {colour: red}", "robot.colour: unknown key (known keys: "),
    ("unknown section", "ekf: {}", "ekff: {}", "ekff: unknown key (did you mean 'ekf'?)"),
    (
        "pins used once",
        "motors: {wheels: {front_left: {enable: 9}}}",
        "motors: {wheels: {front_left: {enable: 4}}}",
        "motors.wheels.front_left.enable: GPIO 4 is already used by encoders.wheels.front_left.a",
    ),
    (
        "key file needed",
        "teleop: {key_file: /etc/k}",
        "teleop: {key_file: ''}",
        "teleop.key_file: required unless teleop.allow_unauthenticated is true",
    ),
    (
        "pose rate bound",
        "pose_socket: {rate_hz: 50}",
        "pose_socket: {rate_hz: 900}\ncontrol: {rate_hz: 10}",
        "pose_socket.rate_hz: must be at most 10x control.rate_hz",
    ),
    ("top level mapping", "{}", "- robot", "<config>: the top level must be a mapping"),
]


@pytest.mark.parametrize(("good", "bad", "expected"), [r[1:] for r in RULES], ids=[r[0] for r in RULES])
def test_each_rule_accepts_the_good_and_names_the_bad(good: str, bad: str, expected: str) -> None:
    assert problems_of(good) == []
    problems = problems_of(bad)
    assert len(problems) == 1, problems
    assert problems[0].startswith(expected), problems[0]


def test_empty_file_gives_the_papers_robot() -> None:
    config = parse("")
    assert config == RobotdConfig()
    assert config.robot.wheel_radius_m == pytest.approx(0.046875)
    assert (config.robot.lx_m, config.robot.ly_m) == (0.135, 0.125)
    assert config.encoders.counts_per_rev == 6800


def test_values_are_converted_and_frozen() -> None:
    config = parse("robot: {lx_m: 1}\nencoders: {decoding: x2, ppr: 100}")
    assert isinstance(config.robot.lx_m, float)
    assert config.encoders.counts_per_rev == 200
    with pytest.raises(AttributeError):
        config.robot.lx_m = 2.0  # type: ignore[misc]


def test_every_problem_is_reported_at_once() -> None:
    problems = problems_of("teleop: {deadman_timeout_s: -1, prot: 5}\ncontrol: {kp: nope}")
    assert sorted(p.split(":")[0] for p in problems) == ["control.kp", "teleop.deadman_timeout_s", "teleop.prot"]


def test_invalid_yaml_names_the_line() -> None:
    problems = problems_of("teleop:\n  port: [1, 2\n")
    assert len(problems) == 1
    assert "invalid YAML at line" in problems[0]


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="no such configuration file"):
        load(tmp_path / "absent.yaml")


def test_shipped_configurations_are_valid(tmp_path: Path) -> None:
    assert main(["check-config", str(REPO / "config" / "sim.yaml")]) == 0
    robot = REPO / "config" / "robot.yaml"
    assert main(["check-config", "--schema-only", str(robot)]) == 0  # its key file lives on the robot
    key = tmp_path / "teleop.key"
    key.write_bytes(b"0123456789abcdef0123456789abcdef\n")
    key.chmod(0o600)
    here = tmp_path / "robot.yaml"
    here.write_text(robot.read_text().replace("/etc/robotd/teleop.key", str(key)))
    assert main(["check-config", str(here)]) == 0


def test_shipped_robot_configuration_documents_every_section() -> None:
    raw = yaml.safe_load((REPO / "config" / "robot.yaml").read_text())
    assert {"robot", "encoders", "motors", "pigpiod", "marvelmind", "ekf", "teleop", "pose_socket", "control"} <= set(
        raw
    )


def test_bad_configuration_exits_78_with_one_line_per_problem_and_no_traceback(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("teleop:\n  deadman_timeout_s: -1\n  max_vx_mps: fast\nrobot:\n  wheel_radus_m: 0.05\n")
    result = subprocess.run(
        [sys.executable, "-m", "robotd", "check-config", str(bad)], capture_output=True, text=True, check=False
    )
    assert result.returncode == EX_CONFIG
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 3, result.stderr
    assert "Traceback" not in result.stderr
    joined = "\n".join(lines)
    for path in ("teleop.deadman_timeout_s", "teleop.max_vx_mps", "robot.wheel_radus_m"):
        assert f": {path}: " in joined


# Every safety limit and its upper bound (item 5 of issue 12): (dotted path, the bound itself, a value beyond it)
UPPER_BOUNDS = [
    ("teleop.deadman_timeout_s", 5.0, 1.0e9),
    ("teleop.max_vx_mps", 3.0, 3.5),
    ("teleop.max_vy_mps", 3.0, 3.5),
    ("teleop.max_wz_rad_s", 10.0, 11.0),
    ("teleop.max_linear_accel_mps2", 10.0, 11.0),
    ("teleop.max_angular_accel_rad_s2", 40.0, 41.0),
    ("teleop.max_datagram_age_s", 1.0, 1.5),
    ("teleop.max_clock_offset_s", 60.0, 61.0),
    ("control.rate_hz", 1000.0, 1001.0),
    ("control.kp", 1.0, 1.5),
    ("control.ki", 10.0, 11.0),
    ("control.kd", 1.0, 1.5),
    ("control.wheel_max_speed_rad_s", 200.0, 201.0),
    ("control.integral_limit", 1.0, 1.5),
    ("motors.duty_limit", 1.0, 1.01),
    ("pose_socket.client_stall_s", 60.0, 61.0),
    ("pose_socket.client_queue", 10_000, 10_001),
    ("pose_socket.max_clients", 128, 129),
    ("marvelmind.stale_after_s", 5.0, 6.0),
    ("marvelmind.reconnect_max_s", 30.0, 31.0),
    ("pigpiod.connect_timeout_s", 5.0, 6.0),
    ("pigpiod.reconnect_max_s", 30.0, 31.0),
]


def _setting(dotted: str, value: object) -> str:
    section, key = dotted.split(".")
    return f"{section}: {{{key}: {value}}}"


@pytest.mark.parametrize(("dotted", "bound", "beyond"), UPPER_BOUNDS, ids=[b[0] for b in UPPER_BOUNDS])
def test_every_safety_limit_has_an_upper_bound(dotted: str, bound: float, beyond: float) -> None:
    assert problems_of(_setting(dotted, bound)) == []
    problems = problems_of(_setting(dotted, beyond))
    assert len(problems) == 1, problems
    assert problems[0].startswith(f"{dotted}: must be "), problems[0]
    assert "at most" in problems[0] or "between" in problems[0]


@pytest.mark.parametrize(
    ("dotted", "floor"),
    [
        ("teleop.max_clock_offset_s", 0),
        ("teleop.deadman_timeout_s", 0),
        ("control.rate_hz", 5),
        ("control.wheel_max_speed_rad_s", 0.5),
    ],
)
def test_limits_that_must_not_be_zero_or_tiny(dotted: str, floor: float) -> None:
    problems = problems_of(_setting(dotted, floor))
    assert len(problems) == 1, problems
    assert problems[0].startswith(f"{dotted}: must be "), problems[0]


def test_each_bound_is_stated_in_its_fields_own_doc() -> None:
    """The doc (not the generated rule) gives the bound, beside its reason."""
    for dotted, bound, _beyond in UPPER_BOUNDS:
        section, key = dotted.split(".")
        cls = type(getattr(RobotdConfig(), section))
        doc = next(f.metadata["doc"] for f in dataclasses.fields(cls) if f.name == key)
        shown = str(int(bound)) if float(bound).is_integer() else str(bound)
        assert shown in doc, (dotted, doc)


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ("a: &x 1\nteleop: {port: *x}", "line 2, column 16: aliases (*name) are not accepted"),
        ("teleop: {port: !!int '47800'}", "line 1, column 16: tags (!name, !!name) are not accepted"),
        ("robot: {ips_offset_m: !!timestamp x}", "tags (!name, !!name) are not accepted"),
        ("a: " + "[" * 40 + "]" * 40, "nested deeper than 32 levels"),
        ("sim: {seed: " + "9" * 5000 + "}", "invalid YAML: Exceeds the limit (4300 digits) for integer string"),
        ("sim: {record_path: 2001-13-01}", "invalid YAML: month must be in 1..12"),
    ],
    ids=["alias", "tag", "crashing tag", "deep nesting", "endless integer", "impossible date"],
)
def test_yaml_that_would_explode_or_crash_is_one_line(text: str, reason: str) -> None:
    problems = problems_of(text)
    assert len(problems) == 1, problems
    assert problems[0].startswith("<config>: invalid YAML"), problems[0]
    assert reason in problems[0], problems[0]


def test_reference_lists_every_key_with_its_real_default() -> None:
    text = config_reference()
    assert "| `teleop.deadman_timeout_s` | number | `0.5` |" in text
    # the front-right encoder's defaults come from its section factory, not the class defaults
    assert "| `encoders.wheels.front_right.a` | integer | `27` |" in text


def test_a_partial_wheel_section_keeps_that_wheels_other_pins() -> None:
    config = parse("motors: {wheels: {rear_right: {sign: -1}}}")
    default = RobotdConfig().motors.wheels.rear_right
    assert config.motors.wheels.rear_right.sign == -1
    assert config.motors.wheels.rear_right.enable == default.enable == 19


def test_readme_blocks_are_current() -> None:
    """The configuration reference, the module map and the figures in the README are what their sources say."""
    readme = (REPO / "README.md").read_text()
    assert current(readme, REPO) == readme, "README is stale: run `make readme` (robotd readme)"


def test_the_import_map_names_each_subpackages_imports_from_its_code(tmp_path: Path) -> None:
    files = {
        "drivers/__init__.py": "",
        "drivers/settings.py": "",
        "drivers/wheels/__init__.py": "",
        "drivers/wheels/motors.py": "from drivers.settings import X\nimport numpy\n",
        "robotd/__init__.py": "",
        "robotd/kinematics.py": "",
        "robotd/daemon/__init__.py": "",
        "robotd/daemon/service.py": "def f():\n    from drivers.wheels.motors import M\n"
        "    from robotd import kinematics\n",
        "robotd/logs/__init__.py": "",
    }
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    rows = {line.split()[0]: line.split("->")[1].strip() for line in import_map(tmp_path).splitlines()[1:-1]}
    assert rows == {
        "drivers/wheels/": "drivers/settings",
        "robotd/daemon/": "drivers/wheels, robotd/kinematics",
        "robotd/logs/": "(nothing of robotd or drivers)",
    }
