"""The fleet section and its secret files: off by default, every problem by its dotted path."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest
from inprocess_daemon import daemon_config

from robotd.config.schema import ConfigError
from robotd.fleet.hook import fleet_link
from robotd.fleet.secrets import load_credentials, load_fleet_key


def test_the_link_is_off_by_default(tmp_path: Path) -> None:
    config = daemon_config(tmp_path)
    assert not config.fleet.enabled
    assert fleet_link(config.fleet, dict, lambda _held: None) is None


@pytest.mark.parametrize(
    ("fleet", "problem"),
    [
        ({"enabled": True, "key_file": "/k"}, "fleet: robot_id: required"),
        ({"enabled": True, "robot_id": "r1"}, "fleet: key_file: required"),
        ({"robot_id": "a/b"}, "fleet.robot_id: must be letters"),
        ({"robot_id": "+"}, "fleet.robot_id: must be letters"),
        ({"robot_id": "fleet"}, "fleet.robot_id: must be letters"),
        ({"pose_rate_hz": 0}, "fleet.pose_rate_hz"),
        ({"port": 0}, "fleet.port"),
    ],
)
def test_a_bad_fleet_section_is_named(tmp_path: Path, fleet: dict[str, object], problem: str) -> None:
    with pytest.raises(ConfigError) as raised:
        daemon_config(tmp_path, fleet=fleet)
    assert any(line.startswith(problem) for line in raised.value.problems), raised.value.problems


def private(path: Path, data: bytes, mode: int = 0o600) -> Path:
    path.write_bytes(data)
    path.chmod(mode)
    return path


def test_secret_files_must_be_private_and_well_formed(tmp_path: Path) -> None:
    assert load_fleet_key(private(tmp_path / "k", b"0123456789abcdef\n")) == b"0123456789abcdef"
    creds = load_credentials(private(tmp_path / "c", b"robot-r1:pa:ss\n"))
    assert (creds.username, creds.password) == ("robot-r1", "pa:ss")
    bad: list[tuple[Callable[[], object], str, str]] = [
        (lambda: load_fleet_key(private(tmp_path / "k2", b"0123456789abcdef", 0o644)), "fleet.key_file: ", "chmod"),
        (lambda: load_fleet_key(private(tmp_path / "k3", b"short")), "fleet.key_file: ", "at least 16"),
        (lambda: load_fleet_key(tmp_path / "missing"), "fleet.key_file: ", "cannot read"),
        (lambda: load_credentials(private(tmp_path / "c2", b"no-colon")), "fleet.credentials_file: ", "username"),
        (lambda: load_credentials(private(tmp_path / "c3", b"a:b\nc:d")), "fleet.credentials_file: ", "one line"),
    ]
    for load, prefix, words in bad:
        with pytest.raises(ConfigError) as raised:
            load()
        (line,) = raised.value.problems
        assert line.startswith(prefix)
        assert words in line


def test_a_daemon_with_a_bad_key_file_does_not_start(tmp_path: Path) -> None:
    from robotd.daemon.service import Daemon  # noqa: PLC0415

    key = private(tmp_path / "k", b"0123456789abcdef", 0o644)
    config = daemon_config(tmp_path, fleet={"enabled": True, "robot_id": "r1", "key_file": str(key)})
    with pytest.raises(ConfigError, match=r"fleet\.key_file"):
        Daemon(config)
