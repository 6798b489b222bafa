"""The doctor's beacon checks: the device is there and streams, fixes come often enough, from our hedgehog, and with
a good quality (Marvelmind's code 0x0007).

Two ways to listen. With robotd stopped, the doctor opens the serial device itself for a few seconds, reading only
(a write stops the beacon's stream for 5 s), and feeds robotd's own parser. With robotd running, the daemon owns the
port and a second reader would split the bytes between the two: the doctor then reads the daemon's status messages
on the pose socket instead. They carry the parser's counters, but not the hedgehog's address nor the quality values.
"""

from __future__ import annotations

import os
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from drivers.marvelmind.events import Position, Quality
from drivers.marvelmind.protocol import MarvelmindParser
from drivers.marvelmind.reader import resolve_device
from robotd.config.model import MarvelmindConfig
from robotd.daemon import poseclient
from robotd.tools.checklist import Finding, failed, passed, skipped

POSITION_CODES = ("0x0001", "0x0011", "0x0081")
MIN_QUALITY_PERCENT = 50
"""Below this the doctor fails the quality (an estimate: Marvelmind publishes no threshold)."""
DAEMON_HOLDS_PORT = "robotd is running and owns the serial port; its status does not carry"


@dataclass(frozen=True, slots=True)
class BeaconSample:
    """What was heard from the beacon in a listening window."""

    source: str  # the device read, or robotd's status
    seconds: float
    frames: int  # frames with a valid CRC, every code
    fixes: int  # valid positions of our hedgehog
    unavailable: int  # "coordinates unavailable"
    other_hedgehogs: int  # frames of another address
    addresses: frozenset[int] | None  # our hedgehog's address as seen (None: not observable from this source)
    qualities: tuple[int, ...] | None  # quality percentages (None: not observable from this source)


def find_device(pattern: str) -> str | None:
    """The device the configuration names, when it exists (a glob resolved as robotd resolves it)."""
    path = resolve_device(pattern)
    return path if path is not None and os.path.exists(path) else None


def listen_serial(path: str, config: MarvelmindConfig, seconds: float) -> BeaconSample:
    """Read the device for `seconds` through robotd's parser, never writing to it (blocking)."""
    import serial  # noqa: PLC0415 - only this check opens a port

    parser = MarvelmindParser(config.hedgehog_address, config.default_latency_s)
    fixes: list[Position] = []
    qualities: list[int] = []
    start = time.monotonic()
    with serial.Serial(path, config.baudrate, timeout=0.1) as port:
        while (now := time.monotonic()) < start + seconds:
            for event in parser.feed(port.read(4096), now):
                if isinstance(event, Position):
                    fixes.append(event)
                elif isinstance(event, Quality):
                    qualities.append(event.quality_percent)
    counters = parser.counters
    return BeaconSample(
        path,
        time.monotonic() - start,
        counters.frames,
        len(fixes),
        counters.unavailable_fixes,
        counters.other_address,
        frozenset(fix.address for fix in fixes),
        tuple(qualities),
    )


def _marvelmind(status: Mapping[str, Any]) -> Mapping[str, Any]:
    drivers = status.get("drivers")
    section = drivers.get("marvelmind") if isinstance(drivers, Mapping) else None
    return section if isinstance(section, Mapping) else {}


def sample_between(first: Mapping[str, Any], last: Mapping[str, Any]) -> BeaconSample:
    """The beacon's traffic between two of the daemon's status messages (from the counters' differences)."""
    a, b = _marvelmind(first), _marvelmind(last)

    def grew(*keys: str, within: str | None = None) -> int:
        old, new = (a.get(within, {}), b.get(within, {})) if within else (a, b)
        return sum(int(new.get(key, 0)) - int(old.get(key, 0)) for key in keys)

    frames_then, frames_now = a.get("frames_by_code", {}), b.get("frames_by_code", {})
    frames = sum(frames_now.values()) - sum(frames_then.values())
    positions = grew(*POSITION_CODES, within="frames_by_code")
    rejected = grew("unavailable_fixes") + grew("other_address") + grew("duplicates")
    return BeaconSample(
        f"robotd's status ({'streaming' if b.get('connected') else b.get('state', 'not streaming')})",
        float(last["t"]) - float(first["t"]),
        frames,
        max(0, positions - rejected),
        grew("unavailable_fixes"),
        grew("other_address"),
        None,
        None,
    )


def listen_daemon(path: str, seconds: float, timeout_s: float) -> BeaconSample:
    """Read the daemon's status messages on its pose socket until two lie `seconds` apart (blocking)."""
    first: dict[str, Any] | None = None
    with poseclient.connect(path, timeout_s) as sock:
        for received in poseclient.messages(sock):
            message = received.message
            if message is None or received.kind != "status":
                continue
            if first is None:
                first = message
            elif float(message["t"]) - float(first["t"]) >= seconds:
                return sample_between(first, message)
    raise OSError("robotd closed its pose socket")


def beacon_findings(config: MarvelmindConfig, device: str | None, sample: BeaconSample | str) -> list[Finding]:
    """The beacon checks from what was heard (`sample` is the reason when nothing could be heard)."""
    if device is None:
        return [
            failed(
                "beacon device",
                f"nothing at {config.device}",
                "plug the beacon in (USB) and link it by its serial number: sudo robotd install --beacon-serial SERIAL"
                " (the serial is the end of its name in ls /dev/serial/by-id)",
            ),
            *(skipped(name, "no beacon device") for name in ("beacon stream", "fix rate", "hedgehog", "quality")),
        ]
    found = [passed("beacon device", f"{config.device}" + (f" -> {device}" if device != config.device else ""))]
    if isinstance(sample, str):
        fix = "run the doctor as root (sudo); if robotd runs, journalctl -u robotd says whether it is answering"
        found.append(failed("beacon stream", f"cannot listen: {sample}", fix))
        return found + [skipped(name, "no beacon stream") for name in ("fix rate", "hedgehog", "quality")]
    window = f"in {sample.seconds:.1f} s from {sample.source}"
    if sample.frames == 0:
        return [
            *found,
            failed(
                "beacon stream",
                f"no frame {window}",
                "wake the hedgehog up and check it streams to USB (Dashboard); is another program reading the port?",
            ),
            *(skipped(name, "no beacon stream") for name in ("fix rate", "hedgehog", "quality")),
        ]
    found.append(passed("beacon stream", f"{sample.frames} frames {window}"))
    return [*found, _fix_rate(config, sample), _address(config, sample), _quality(sample)]


def _fix_rate(config: MarvelmindConfig, sample: BeaconSample) -> Finding:
    rate = sample.fixes / sample.seconds if sample.seconds > 0 else 0.0
    needed = 1.0 / config.stale_after_s
    seen = f"{rate:.1f} fixes/s, {sample.unavailable} 'coordinates unavailable'"
    if rate >= needed:
        return passed("fix rate", f"{seen} (at least {needed:.1f}/s keeps a fix fresh: marvelmind.stale_after_s)")
    if sample.unavailable > sample.fixes:
        fix = "the hedgehog cannot locate itself: free its line of sight to the stationary beacons, freeze the map"
    else:
        slower = 2.0 / rate if rate > 0 else 5.0
        fix = f"raise the update rate (a smaller submap) or marvelmind.stale_after_s to {min(slower, 5.0):.1f}"
    return failed("fix rate", f"{seen}: slower than {needed:.1f}/s, so the fix goes stale between fixes", fix)


def _address(config: MarvelmindConfig, sample: BeaconSample) -> Finding:
    if sample.addresses is None:
        return skipped("hedgehog", f"{DAEMON_HOLDS_PORT} the hedgehog's address: stop robotd to check it")
    configured = config.hedgehog_address
    ours = ", ".join(str(a) for a in sorted(sample.addresses))
    if configured != "auto":
        if sample.addresses:
            return passed("hedgehog", f"address {ours}, as marvelmind.hedgehog_address says")
        return failed(
            "hedgehog",
            f"no fix from address {configured}; {sample.other_hedgehogs} frames of other hedgehogs",
            "set marvelmind.hedgehog_address to your hedgehog's address (Dashboard), or auto",
        )
    if sample.other_hedgehogs:
        return failed(
            "hedgehog",
            f"auto followed address {ours or '?'}, but {sample.other_hedgehogs} frames came from other hedgehogs",
            f"set marvelmind.hedgehog_address to yours{f' ({ours})' if ours else ''}: auto follows the first heard",
        )
    if not sample.addresses:
        return skipped("hedgehog", "no valid fix in the window, so no address was learnt")
    return passed("hedgehog", f"address {ours}, the only one heard (marvelmind.hedgehog_address: auto)")


def _quality(sample: BeaconSample) -> Finding:
    if sample.qualities is None:
        return skipped("quality", f"{DAEMON_HOLDS_PORT} the quality values: stop robotd to check them")
    if not sample.qualities:
        return skipped(
            "quality",
            f"no quality frame (code 0x0007) in {sample.seconds:.1f} s: to check it, stream it (Dashboard,"
            " the modem's interface settings)",
        )
    lowest = min(sample.qualities)
    if lowest < MIN_QUALITY_PERCENT:
        return failed(
            "quality",
            f"as low as {lowest} % (below {MIN_QUALITY_PERCENT} %)",
            "place the stationary beacons higher and in sight of the hedgehog; keep ultrasonic noise away",
        )
    return passed("quality", f"{lowest} % or better over {len(sample.qualities)} frames")
