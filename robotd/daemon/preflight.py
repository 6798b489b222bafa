"""Start-up checks of what a valid configuration names on this host: the teleop key file and the bind address.

`robotd check-config` and `robotd run` both call `preflight()`, so a configuration that check-config accepts starts.
These checks touch the file system and the network stack, which `robotd.config.model.parse` (pure) never does.
"""

from __future__ import annotations

import ipaddress
import socket

from robotd.config.gpio import gpiod_problems, resolve_backend
from robotd.config.model import RobotdConfig
from robotd.config.schema import ConfigError
from robotd.daemon.teleop import check_key_file


def bind_problems(address: str, dotted: str) -> list[str]:
    """Problems binding a UDP socket to `address` on this host (on a free port, so nothing else is disturbed)."""
    family = socket.AF_INET6 if ipaddress.ip_address(address).version == 6 else socket.AF_INET
    try:
        with socket.socket(family, socket.SOCK_DGRAM) as probe:
            probe.bind((address, 0))
    except OSError as error:
        return [f"{dotted}: cannot listen on {address} on this host: {error.strerror or error}"]
    return []


def host_problems(config: RobotdConfig) -> list[str]:
    """Every problem of the files and addresses the configuration names, one line each with its dotted path."""
    problems: list[str] = []
    if config.teleop.key_file:
        problems += check_key_file(config.teleop.key_file)
    problems += bind_problems(config.teleop.bind, "teleop.bind")
    if config.gpio.backend == "auto" and resolve_backend(config.gpio) == "gpiod":  # explicit gpiod: checked by parse
        problems += gpiod_problems(config.motors)
    return problems


def preflight(config: RobotdConfig) -> None:
    """Raise ConfigError listing every host problem of `config`; return when there is none."""
    problems = host_problems(config)
    if problems:
        raise ConfigError(problems)
