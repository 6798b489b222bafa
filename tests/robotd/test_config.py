"""Configuration: every validation rule with a failing and a passing example, and the CLI's exit status 78."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from robotd.cli import EX_CONFIG, main
from robotd.config import RobotdConfig, config_reference, load, parse
from robotd.readme import current
from robotd.schema import ConfigError

REPO = Path(__file__).resolve().parents[2]


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
        "teleop.deadman_timeout_s: must be > 0, got -1",
    ),
    (
        "positive rejects zero",
        "robot: {wheel_radius_m: 0.05}",
        "robot: {wheel_radius_m: 0}",
        "robot.wheel_radius_m: must be > 0, got 0",
    ),
    ("non-negative", "control: {kd: 0}", "control: {kd: -0.5}", "control.kd: must be >= 0, got -0.5"),
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
    ("octal mode", "pose_socket: {mode: '0640'}", "pose_socket: {mode: '0999'}", "pose_socket: mode must be octal"),
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


@pytest.mark.parametrize("name", ["robot.yaml", "sim.yaml"])
def test_shipped_configurations_are_valid(name: str) -> None:
    assert main(["check-config", str(REPO / "config" / name)]) == 0


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
