"""The fleet link's secrets: the broker credentials, the fleet key, and the TLS context, each from a file.

Like teleop's key file: a file owned by root may be shared with the daemon's group (0640), any other owner must keep
it to itself (0600). Every problem is a ConfigError naming the configuration field, so a bad file stops the daemon at
start-up (exit 78), never later.
"""

from __future__ import annotations

import ssl
import stat
from dataclasses import dataclass
from pathlib import Path

from robotd.config.fleet import FleetConfig
from robotd.config.schema import ConfigError
from robotd.config.smallfile import SmallFileError, read_small_file, regular_file

MIN_KEY_BYTES = 16
MAX_SECRET_FILE_BYTES = 4096


@dataclass(frozen=True, slots=True)
class Credentials:
    """A broker user name and password."""

    username: str
    password: str


def _read_private(path: str | Path, field: str) -> bytes:
    try:
        info = regular_file(path)
        data = read_small_file(path, MAX_SECRET_FILE_BYTES).strip()
    except SmallFileError as error:
        raise ConfigError([f"{field}: cannot read {path}: {error}"]) from None
    allowed = 0o640 if info.st_uid == 0 else 0o600
    mode = stat.S_IMODE(info.st_mode)
    if mode & ~allowed:
        raise ConfigError(
            [f"{field}: {path} has mode {mode:04o}, so other users can read it: run `chmod {allowed:04o} {path}`"]
        )
    return data


def load_fleet_key(path: str | Path, field: str = "fleet.key_file") -> bytes:
    """The fleet's HMAC key from a private key file, or ConfigError."""
    key = _read_private(path, field)
    if len(key) < MIN_KEY_BYTES:
        raise ConfigError([f"{field}: {path} holds {len(key)} bytes; a key needs at least {MIN_KEY_BYTES}"])
    return key


def load_credentials(path: str | Path, field: str = "fleet.credentials_file") -> Credentials:
    """`username:password` from a private one-line file, or ConfigError."""
    try:
        text = _read_private(path, field).decode("utf-8")
    except UnicodeDecodeError:
        raise ConfigError([f"{field}: {path} is not UTF-8 text"]) from None
    username, colon, password = text.partition(":")
    if not colon or not username or "\n" in text:
        raise ConfigError([f"{field}: {path} must hold one line `username:password`"])
    return Credentials(username, password)


def tls_context(config: FleetConfig) -> ssl.SSLContext | None:
    """A client TLS context verifying the broker (with fleet.ca_file when set), or None without TLS."""
    if not config.tls:
        return None
    try:
        return ssl.create_default_context(cafile=config.ca_file or None)
    except (OSError, ssl.SSLError) as error:
        raise ConfigError([f"fleet.ca_file: cannot load {config.ca_file}: {error}"]) from None
