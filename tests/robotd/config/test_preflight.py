"""`robotd check-config` and `robotd run` refuse, at start, what would hang, crash or expose the daemon later.

Every case: exit 78, one line naming the dotted path, no traceback, and quickly (the timeout marker fails a hang).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
from paths import REPO

from robotd.cli import EX_CONFIG, main
from robotd.config.schema import ConfigError
from robotd.daemon.teleop import load_key

KEY = b"0123456789abcdef0123456789abcdef"

pytestmark = pytest.mark.timeout(10)


def write_config(tmp_path: Path, teleop: str, extra: str = "") -> Path:
    """A configuration whose teleop section is `teleop` (YAML flow mapping body), other sections as given."""
    config = tmp_path / "robot.yaml"
    config.write_text(
        f"teleop: {{bind: 127.0.0.1, {teleop}}}\npose_socket: {{path: {tmp_path / 'pose.sock'}}}\n{extra}"
    )
    return config


def key_file(tmp_path: Path, content: bytes = KEY, mode: int = 0o600) -> Path:
    """A key file with that content and mode."""
    path = tmp_path / "teleop.key"
    path.write_bytes(content)
    path.chmod(mode)
    return path


def refused(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    """Run the command line in-process, expecting exit 78 with exactly one line; that line."""
    status = main(argv)
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert status == EX_CONFIG, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    return lines[0]


def check_and_run_refuse(config: Path, dotted: str, capsys: pytest.CaptureFixture[str]) -> str:
    """Both `check-config` and `run` refuse `config` with one line on `dotted`; that line."""
    line = refused(["check-config", str(config)], capsys)
    assert line.startswith(f"robotd: config: {dotted}: "), line
    assert refused(["run", "--config", str(config)], capsys) == line  # run refuses before it starts anything
    return line


def test_a_good_key_file_passes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = write_config(tmp_path, f"key_file: {key_file(tmp_path)}")
    assert main(["check-config", str(config)]) == 0
    assert capsys.readouterr().out.strip() == f"{config}: ok"


# --- the key file ----------------------------------------------------------------------------------------------


def _missing(tmp_path: Path) -> Path:
    return tmp_path / "absent.key"


def _short(tmp_path: Path) -> Path:
    return key_file(tmp_path, b"too short\n")


def _empty(tmp_path: Path) -> Path:
    return key_file(tmp_path, b"")


def _directory(tmp_path: Path) -> Path:
    path = tmp_path / "keys"
    path.mkdir(mode=0o700)
    return path


def _fifo(tmp_path: Path) -> Path:
    path = tmp_path / "teleop.fifo"
    os.mkfifo(path, 0o600)  # opening it for reading blocks until a writer comes: there is none
    return path


def _huge(tmp_path: Path) -> Path:
    return key_file(tmp_path, b"k" * 100_000)


KEY_FILES: list[tuple[str, Callable[[Path], Path], str]] = [
    ("missing", _missing, "No such file or directory"),
    ("short", _short, "holds 9 bytes; a key needs at least 16"),
    ("empty", _empty, "holds 0 bytes; a key needs at least 16"),
    ("directory", _directory, "is a directory, not a regular file"),
    ("dev zero", lambda _tmp: Path("/dev/zero"), "is a character device, not a regular file"),
    ("fifo", _fifo, "is a FIFO (named pipe), not a regular file"),
    ("too large", _huge, "holds 100000 bytes, more than the 4096 allowed"),
]


@pytest.mark.parametrize(("make", "reason"), [k[1:] for k in KEY_FILES], ids=[k[0] for k in KEY_FILES])
def test_an_unusable_key_file_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], make: Callable[[Path], Path], reason: str
) -> None:
    path = make(tmp_path)
    line = check_and_run_refuse(write_config(tmp_path, f"key_file: {path}"), "teleop.key_file", capsys)
    assert str(path) in line
    assert line.endswith(reason), line


@pytest.mark.parametrize("make", [_fifo, lambda _tmp: Path("/dev/zero")], ids=["fifo", "dev zero"])
def test_load_key_itself_never_blocks_nor_reads_without_end(tmp_path: Path, make: Callable[[Path], Path]) -> None:
    with pytest.raises(ConfigError, match="not a regular file"):
        load_key(make(tmp_path))


def test_an_unreadable_key_file_is_refused(tmp_path: Path) -> None:
    path = key_file(tmp_path, mode=0o000)
    config = write_config(tmp_path, f"key_file: {path}")
    command = [sys.executable, "-m", "robotd", "check-config", str(config)]
    if os.geteuid() == 0:  # root reads any file: take away the two capabilities that let it
        setpriv = shutil.which("setpriv")
        if setpriv is None:
            pytest.skip("running as root without setpriv: cannot make a file unreadable")
        command = [setpriv, "--bounding-set", "-dac_override,-dac_read_search", *command]
    result = subprocess.run(
        command, cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True, text=True, check=False
    )
    assert result.returncode == EX_CONFIG, result.stderr
    assert "Traceback" not in result.stderr
    assert result.stderr.strip() == f"robotd: config: teleop.key_file: cannot read {path}: Permission denied"


def test_a_key_other_users_can_read_is_refused_with_the_chmod_that_fixes_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = key_file(tmp_path, mode=0o644)
    config = write_config(tmp_path, f"key_file: {path}")
    line = check_and_run_refuse(config, "teleop.key_file", capsys)
    assert "has mode 0644" in line
    chmod = line.split("run `")[1].rstrip("`").split()
    assert chmod[0] == "chmod"
    path.chmod(int(chmod[1], 8))
    assert main(["check-config", str(config)]) == 0


def test_a_group_readable_key_is_refused_unless_root_owns_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """As PostgreSQL: root:robotd 0640 (the README's install) is fine; a key of any other owner stays 0600."""
    path = key_file(tmp_path, mode=0o640)
    config = write_config(tmp_path, f"key_file: {path}")
    if os.geteuid() == 0:
        assert main(["check-config", str(config)]) == 0
        os.chown(path, 65534, 65534)  # root may give it away; then the group must not read it
    line = check_and_run_refuse(config, "teleop.key_file", capsys)
    assert line.endswith(f"run `chmod 0600 {path}`")


# --- who may drive, and where ----------------------------------------------------------------------------------


def test_no_authentication_together_with_a_key_file_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = write_config(tmp_path, f"key_file: {key_file(tmp_path)}, allow_unauthenticated: true")
    line = check_and_run_refuse(config, "teleop.allow_unauthenticated", capsys)
    assert "unsigned datagrams" in line


def test_teleop_without_a_key_must_listen_on_loopback(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = tmp_path / "robot.yaml"
    config.write_text("teleop: {bind: 0.0.0.0, key_file: '', allow_unauthenticated: true}\n")
    assert "loopback" in check_and_run_refuse(config, "teleop.bind", capsys)
    config.write_text("teleop: {bind: 127.0.0.2, key_file: '', allow_unauthenticated: true}\n")  # all of 127/8
    assert main(["check-config", str(config)]) == 0


@pytest.mark.parametrize(
    ("bind", "reason"),
    [
        ("999.0.0.1", "must be an IP address"),
        ("localhost", "must be an IP address"),
        ("192.0.2.1", "cannot listen on 192.0.2.1 on this host"),  # TEST-NET-1: no host has it
    ],
)
def test_a_bind_address_that_cannot_be_bound_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], bind: str, reason: str
) -> None:
    config = write_config(tmp_path, f"key_file: {key_file(tmp_path)}")
    config.write_text(config.read_text().replace("bind: 127.0.0.1", f"bind: {bind}"))
    assert reason in check_and_run_refuse(config, "teleop.bind", capsys)


def test_a_pigpiod_host_written_as_an_address_must_be_one(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = write_config(tmp_path, f"key_file: {key_file(tmp_path)}", "pigpiod: {host: 127.0.0.300}\n")
    check_and_run_refuse(config, "pigpiod.host", capsys)
    config.write_text(config.read_text().replace("127.0.0.300", "robot-pi.local"))
    assert main(["check-config", str(config)]) == 0  # a host name is resolved when pigpiod is reached


@pytest.mark.parametrize(
    ("mode", "reason"),
    [
        ("7777", "setuid, setgid or sticky"),
        ("4660", "setuid, setgid or sticky"),
        ("0666", "writable by every user"),
        ("0999", "octal permissions"),
        ("rw-rw----", "octal permissions"),
    ],
)
def test_the_pose_socket_mode_must_be_a_safe_file_mode(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], mode: str, reason: str
) -> None:
    config = write_config(tmp_path, f"key_file: {key_file(tmp_path)}", f"pose_socket: {{mode: '{mode}'}}\n")
    config.write_text(config.read_text().replace(f"pose_socket: {{path: {tmp_path / 'pose.sock'}}}\n", ""))
    assert reason in check_and_run_refuse(config, "pose_socket.mode", capsys)


# --- the YAML itself -------------------------------------------------------------------------------------------

BILLION_LAUGHS = "\n".join(
    [
        "a: &a [0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1]",
        *(f"{b}: &{b} [{', '.join([f'*{a}'] * 9)}]" for a, b in zip("abcdefgh", "bcdefghi", strict=True)),
        "ekf: {initial_pose: *i}",
        "",
    ]
)


def test_billion_laughs_is_refused_at_once(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = tmp_path / "robot.yaml"
    config.write_text(BILLION_LAUGHS)
    line = refused(["check-config", str(config)], capsys)
    assert line == (
        f"robotd: config: {config}: invalid YAML at line 2, column 8:"
        " aliases (*name) are not accepted in a configuration: write the value out"
    )
    assert refused(["run", "--config", str(config)], capsys) == line


def test_a_non_number_inside_a_numeric_list_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = tmp_path / "robot.yaml"
    config.write_text("ekf: {initial_sigma: [1.0, wide, 3.14]}\n")
    line = refused(["check-config", str(config)], capsys)
    assert line == "robotd: config: ekf.initial_sigma[1]: expected a number, got string 'wide'"


@pytest.mark.parametrize(
    ("path", "reason"),
    [("/dev/zero", "is a character device, not a regular file"), ("fifo", "is a FIFO (named pipe)")],
)
def test_a_configuration_path_that_is_no_file_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], path: str, reason: str
) -> None:
    if path == "fifo":
        path = str(_fifo(tmp_path))
    line = refused(["check-config", path], capsys)
    assert line.startswith(f"robotd: config: {path}: cannot read: {reason}"), line


def test_an_oversized_configuration_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = tmp_path / "robot.yaml"
    config.write_text("# padding\n" * 200_000)
    line = refused(["check-config", str(config)], capsys)
    assert line.startswith(f"robotd: config: {config}: cannot read: holds 2000000 bytes, more than the 1048576 allowed")


def test_the_real_command_line_says_one_line_for_a_fifo_key(tmp_path: Path) -> None:
    """End to end, as an operator runs it: `robotd run` on a FIFO key file returns at once with exit 78."""
    config = write_config(tmp_path, f"key_file: {_fifo(tmp_path)}")
    result = subprocess.run(
        [sys.executable, "-m", "robotd", "run", "--config", str(config)],
        cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        capture_output=True,
        text=True,
        timeout=8,
        check=False,
    )
    assert result.returncode == EX_CONFIG
    assert "Traceback" not in result.stderr
    assert result.stderr.strip().startswith("robotd: config: teleop.key_file: cannot read ")
