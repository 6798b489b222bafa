"""Events of the Marvelmind parser: frozen, slotted dataclasses in SI units (m, s, rad, m/s, T), plus its counters.

Every event carries `arrival`, the host's monotonic time (s) at which the bytes completing its frame were read, and
`code`, the frame's streaming code, so that `frames.encode_event` can rebuild the exact frame.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields

Vector3 = tuple[float, float, float]

ANGLE_HEADING_MASK = 0x0FFF  # bits 0-11: heading of a hedgehog pair, tenths of a degree
ANGLE_PAIR_CENTRE = 0x1000  # bit 12: the coordinates are for the pair's centre
ANGLE_HEADING_NOT_APPLICABLE = 0x2000  # bit 13


@dataclass(frozen=True, slots=True)
class Position:
    """A valid fix of a mobile beacon (codes 0x0001, 0x0011, 0x0081)."""

    arrival: float  # s, host clock
    t_meas: float  # s, host clock: arrival minus the time shift (or the default latency when it is unknown)
    x: float  # m
    y: float  # m
    z: float  # m
    address: int
    timestamp: int  # the beacon's raw counter (restarts on wake-up, wraps): for order and duplicates only
    timestamp_s: float  # the same counter in seconds (flags bit 1 selects ms or 1/64 s)
    flags: int
    angle_word: int  # raw; see `heading_rad`
    time_shift_s: float  # s from the ultrasound emission to the sending of the frame; 0.0 = unknown
    code: int
    velocity: Vector3 | None = None  # m/s, from the 0x0081 speed extension when present

    @property
    def heading_rad(self) -> float | None:
        """Heading of a hedgehog pair (rad), or None when the beacon says it is not applicable."""
        if self.angle_word & ANGLE_HEADING_NOT_APPLICABLE:
            return None
        return math.radians((self.angle_word & ANGLE_HEADING_MASK) / 10.0)


@dataclass(frozen=True, slots=True)
class FixUnavailable:
    """A position frame flagged "coordinates unavailable" (flags bit 0): its x, y, z are never exposed."""

    arrival: float
    address: int
    timestamp: int
    timestamp_s: float
    flags: int
    code: int


@dataclass(frozen=True, slots=True)
class StationaryBeacon:
    """One stationary beacon of the map."""

    address: int
    x: float  # m
    y: float  # m
    z: float  # m
    applicable: bool = True  # 0x0012 flags bit 0 clear; always True for 0x0002


@dataclass(frozen=True, slots=True)
class StationaryBeacons:
    """The positions of the stationary beacons (codes 0x0002, 0x0012)."""

    arrival: float
    beacons: tuple[StationaryBeacon, ...]
    code: int


@dataclass(frozen=True, slots=True)
class RawImu:
    """Raw inertial sensors (codes 0x0003, 0x0083); a sensor flagged not available is None."""

    arrival: float
    address: int
    timestamp: int  # ms
    timestamp_s: float
    acceleration: Vector3 | None  # m/s^2
    angular_velocity: Vector3 | None  # rad/s
    magnetic_field: Vector3 | None  # T
    flags: int
    code: int


@dataclass(frozen=True, slots=True)
class Distance:
    """One hedgehog-to-beacon distance of a raw distances frame."""

    beacon: int  # address of the stationary beacon
    distance: float  # m
    valid: bool  # item flags bit 0 clear


@dataclass(frozen=True, slots=True)
class RawDistances:
    """Raw distances from a hedgehog to up to four beacons (codes 0x0004, 0x0084); empty items are left out."""

    arrival: float
    t_meas: float
    address: int
    timestamp: int  # ms
    timestamp_s: float
    time_shift_s: float
    distances: tuple[Distance, ...]
    code: int


@dataclass(frozen=True, slots=True)
class ImuFusion:
    """The beacon's IMU-fused state (codes 0x0005, 0x0085); a part flagged not available is None."""

    arrival: float
    address: int
    timestamp: int  # ms
    timestamp_s: float
    position: Vector3 | None  # m
    quaternion: tuple[float, float, float, float] | None  # w, x, y, z
    velocity: Vector3 | None  # m/s
    acceleration: Vector3 | None  # m/s^2
    flags: int
    code: int


@dataclass(frozen=True, slots=True)
class Telemetry:
    """Battery and radio telemetry (code 0x0006)."""

    arrival: float
    address: int
    battery_v: float
    rssi_dbm: int
    code: int


@dataclass(frozen=True, slots=True)
class Quality:
    """Positioning quality and geofence alarm (code 0x0007)."""

    arrival: float
    address: int
    quality_percent: int
    geofence_zone: int  # 0 = no alarm
    code: int


Event = Position | FixUnavailable | StationaryBeacons | RawImu | RawDistances | ImuFusion | Telemetry | Quality

EVENT_TYPES: dict[type[Event], str] = {
    Position: "position",
    FixUnavailable: "fix_unavailable",
    StationaryBeacons: "stationary_beacons",
    RawImu: "raw_imu",
    RawDistances: "raw_distances",
    ImuFusion: "imu_fusion",
    Telemetry: "telemetry",
    Quality: "quality",
}


def event_as_dict(event: Event) -> dict[str, object]:
    """A JSON-ready mapping of an event: its `type` name, then its fields (and a position's heading)."""
    record: dict[str, object] = {"type": EVENT_TYPES[type(event)], **asdict(event)}
    if isinstance(event, Position):
        record["heading_rad"] = event.heading_rad
    return record


@dataclass(slots=True)
class Counters:
    """What the parser has seen (every byte is either in a frame or counted as junk), and the reader's map refusals."""

    frames_by_code: dict[int, int] = field(default_factory=dict)  # frames with a valid CRC, before any filtering
    crc_failures: int = 0
    junk_bytes: int = 0
    size_rejections: int = 0  # known code with a payload size it never has
    unknown_codes: int = 0  # a header with a code outside the whitelist
    false_headers: int = 0  # a header whose claimed frame wholly holds a valid frame
    truncated: int = 0  # a header still incomplete at the end of the stream
    unavailable_fixes: int = 0
    other_address: int = 0  # frames for another hedgehog (flags bit 6 or another address)
    duplicates: int = 0  # same timestamp as the previous frame of its kind
    address_changes: int = 0  # under auto: our hedgehog's address learnt again as another one
    outside_map: int = 0  # fixes refused by the reader as outside the map (drivers.marvelmind.mapbound)

    @property
    def frames(self) -> int:
        """Frames with a valid CRC, all codes."""
        return sum(self.frames_by_code.values())

    def as_dict(self) -> dict[str, object]:
        """A JSON-ready copy; codes as 0x hex strings."""
        result: dict[str, object] = {}
        for fld in fields(self):
            value = getattr(self, fld.name)
            if fld.name == "frames_by_code":
                value = {f"0x{code:04x}": count for code, count in sorted(value.items())}
            result[fld.name] = value
        return result
