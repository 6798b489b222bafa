"""How the daemon builds its fleet link: None while `fleet.enabled` is off, so a robot alone imports no MQTT."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from robotd.config.fleet import FleetConfig

if TYPE_CHECKING:
    from robotd.fleet.link import FleetLink


def fleet_link(
    config: FleetConfig, status_source: Callable[[], dict[str, Any]], on_hold: Callable[[bool], None]
) -> FleetLink | None:
    """The link for `config` (its key and credentials read now: a bad file is a ConfigError at start-up), or None."""
    if not config.enabled:
        return None
    from robotd.fleet.link import FleetLink  # noqa: PLC0415 - aiomqtt and paho only for robots in a fleet

    return FleetLink(config, status_source=status_source, on_hold=on_hold)
