"""The Marvelmind hedgehog protocol, sans-I/O: `feed(bytes, arrival) -> list[Event]`.

Theory of operation: `FrameScanner` finds CRC-valid frames; this module decodes each payload (tables in
marvelmind-protocol.md) into an event in SI units and applies the semantics the vendor's parsers miss:
- flags bit 0 ("coordinates unavailable") yields `FixUnavailable`, never a `Position`;
- flags bit 1 selects the timestamp unit (1 = ms, 0 = 1/64 s, firmware before 5.20);
- flags bit 6 (data for another hedgehog) and, once known, any address other than our hedgehog's drop the frame.
  With `hedgehog_address="auto"` the address is learnt from the first position frame without bit 6, and learnt again
  (re-latched) when our hedgehog has sent no position frame for `relatch_after_s` while another address sent
  RELATCH_FRAMES of them without bit 6 (a hedgehog swapped on a port that never closed); `forget_address()` makes the
  next position frame teach it (the reader calls it when the port is reopened: another device may be behind it);
- a frame whose timestamp equals the previous one of its kind is a duplicate and dropped;
- `t_meas = arrival - time_shift`, or `arrival - default_latency_s` when the time-shift field is 0 (unknown).
No serial port, no asyncio, no clock: the caller passes the arrival time of each piece of bytes.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from typing import Literal

from drivers.marvelmind.events import (
    Counters,
    Distance,
    Event,
    FixUnavailable,
    ImuFusion,
    Position,
    Quality,
    RawDistances,
    RawImu,
    StationaryBeacon,
    StationaryBeacons,
    Telemetry,
)
from drivers.marvelmind.framing import Frame, FrameScanner

# Flags byte of the position codes.
FLAG_UNAVAILABLE = 0x01
FLAG_TIMESTAMP_MS = 0x02
FLAG_OTHER_HEDGEHOG = 0x40

# Unit conversions to SI (the scale of one least significant bit).
# Lengths and times are divided by their count per SI unit: division is correctly rounded, so 7 cm is exactly 0.07.
CM_PER_M = 100.0
MM_PER_M = 1000.0
MS_PER_S = 1000.0
TICKS_PER_S_OLD = 64.0  # the 1/64 s timestamp unit of firmware before 5.20
STANDARD_GRAVITY = 9.80665
ACCEL_LSB = 1e-3 * STANDARD_GRAVITY  # 1 mg
GYRO_LSB = math.radians(0.0175)  # 0.0175 deg/s
GAUSS = 1e-4  # T
COMPASS_XY_LSB = GAUSS / 1100.0
COMPASS_Z_LSB = GAUSS / 980.0
QUATERNION_LSB = 1e-4
BATTERY_LSB = 1e-3  # mV

# Payload layouts (little-endian; `x` is a reserved byte).
POSITION_CM = struct.Struct("<I3hBBHH")
POSITION_MM = struct.Struct("<I3iBBHH")
POSITION_MM64 = struct.Struct("<q3iBBHH")
SPEED_RECORD = struct.Struct("<B3h")  # 0x0081 extension: subcode 1, vx, vy, vz mm/s
SUBCODE_SPEED = 1
BEACON_CM = struct.Struct("<B3hx")
BEACON_MM = struct.Struct("<B3iB")
RAW_IMU = struct.Struct("<3h3h3hB5xIB3x")
RAW_IMU64 = struct.Struct("<3h3h3hB5xqB3x")
DISTANCE_ITEMS = "BIB" * 4
RAW_DISTANCES = struct.Struct(f"<B{DISTANCE_ITEMS}IHx")
RAW_DISTANCES64 = struct.Struct(f"<B{DISTANCE_ITEMS}qHx")
IMU_FUSION = struct.Struct("<3i4h3h3hBxIB3x")
IMU_FUSION64 = struct.Struct("<3i4h3h3hBxqB3x")
TELEMETRY = struct.Struct("<HbB12x")
QUALITY = struct.Struct("<BBB13x")

# Flags of the IMU codes: bit set = that part is not available.
IMU_ACCEL_NA, IMU_GYRO_NA, IMU_COMPASS_NA = 0x01, 0x02, 0x04
FUSION_POSITION_NA, FUSION_QUATERNION_NA, FUSION_VELOCITY_NA, FUSION_ACCEL_NA = 0x01, 0x02, 0x04, 0x08
ITEM_NA = 0x01  # raw distance item, stationary beacon (0x0012)

Decoder = Callable[[int, bytes, float], Event | None]
RELATCH_FRAMES = 3  # one stray frame of another address is not a hedgehog that streams


class MarvelmindParser:
    """Bytes of a hedgehog's (or modem's) stream in, events of our hedgehog out."""

    def __init__(
        self,
        hedgehog_address: int | Literal["auto"] = "auto",
        default_latency_s: float = 0.05,
        relatch_after_s: float = 2.0,
    ) -> None:
        if hedgehog_address != "auto" and not (isinstance(hedgehog_address, int) and 0 <= hedgehog_address <= 255):
            raise ValueError(f"hedgehog_address must be 0..255 or 'auto', got {hedgehog_address!r}")
        if not (math.isfinite(default_latency_s) and default_latency_s >= 0.0):
            raise ValueError(f"default_latency_s must be a finite number >= 0, got {default_latency_s!r}")
        if not (math.isfinite(relatch_after_s) and relatch_after_s > 0.0):
            raise ValueError(f"relatch_after_s must be a finite number > 0, got {relatch_after_s!r}")
        self.counters = Counters()
        self.default_latency_s = default_latency_s
        self.relatch_after_s = relatch_after_s
        self.auto = hedgehog_address == "auto"
        self.hedgehog_address: int | None = None if hedgehog_address == "auto" else hedgehog_address
        """Our hedgehog's address: configured, learnt (auto) or None while still unknown."""
        self.previous_address: int | None = None
        """Under auto, the address followed before the last change (None before any change)."""
        self._heard_at = -math.inf  # arrival of our hedgehog's last position frame
        self._candidate = (-1, 0)  # under auto: another address and how many position frames it sent meanwhile
        self._scanner = FrameScanner(self.counters)
        self._last_timestamp: dict[str, int] = {}
        self._decoders: dict[int, Decoder] = {
            0x0001: self._position,
            0x0011: self._position,
            0x0081: self._position,
            0x0002: self._beacons,
            0x0012: self._beacons,
            0x0003: self._raw_imu,
            0x0083: self._raw_imu,
            0x0004: self._raw_distances,
            0x0084: self._raw_distances,
            0x0005: self._imu_fusion,
            0x0085: self._imu_fusion,
            0x0006: self._telemetry,
            0x0007: self._quality,
        }

    @property
    def pending(self) -> int:
        """Bytes held for a frame that may still complete (always < 262)."""
        return self._scanner.pending

    def feed(self, data: bytes | bytearray | memoryview, arrival: float) -> list[Event]:
        """The events of the frames completed by `data`, which arrived at `arrival` (s, host monotonic clock)."""
        return self._decode(self._scanner.feed(data), arrival)

    def finish(self) -> None:
        """End of stream: the bytes still held (an incomplete frame) are counted as junk."""
        self._scanner.finish()

    def forget_address(self) -> None:
        """Under auto: learn our hedgehog's address again from the next position frame (a configured one stays)."""
        if self.auto and self.hedgehog_address is not None:
            self.previous_address, self.hedgehog_address = self.hedgehog_address, None
            self._last_timestamp.clear()  # another device's counter: its first frame is not a duplicate

    def _decode(self, frames: list[Frame], arrival: float) -> list[Event]:
        events: list[Event] = []
        by_code = self.counters.frames_by_code
        decoders = self._decoders
        for code, payload in frames:
            by_code[code] = by_code.get(code, 0) + 1
            event = decoders[code](code, payload, arrival)
            if event is not None:
                events.append(event)
        return events

    # --- semantics shared by the codes ------------------------------------------------------------------------

    def _is_ours(self, address: int) -> bool:
        """False (and counted) for another hedgehog's frame, once our address is known."""
        if self.hedgehog_address is None or address == self.hedgehog_address:
            return True
        self.counters.other_address += 1
        return False

    def _relatches(self, address: int, arrival: float) -> bool:
        """Under auto: whether this position frame of another address makes it ours (our hedgehog being silent)."""
        if not self.auto:
            return False
        other, frames = self._candidate
        self._candidate = (address, frames + 1 if other == address else 1)
        if self._candidate[1] < RELATCH_FRAMES or arrival - self._heard_at < self.relatch_after_s:
            return False
        self.previous_address, self.hedgehog_address = self.hedgehog_address, address
        self.counters.address_changes += 1
        self._last_timestamp.clear()
        return True

    def _is_duplicate(self, kind: str, timestamp: int) -> bool:
        """True (and counted) when the timestamp repeats the previous one of this kind of frame."""
        if self._last_timestamp.get(kind) == timestamp:
            self.counters.duplicates += 1
            return True
        self._last_timestamp[kind] = timestamp
        return False

    def _t_meas(self, arrival: float, time_shift_ms: int) -> float:
        return arrival - (time_shift_ms / MS_PER_S if time_shift_ms else self.default_latency_s)

    # --- one decoder per payload layout -------------------------------------------------------------------------

    def _position(self, code: int, payload: bytes, arrival: float) -> Event | None:
        velocity = None
        if code == 0x0001:
            timestamp, x, y, z, flags, address, angle_word, time_shift = POSITION_CM.unpack(payload)
            per_m = CM_PER_M
        elif code == 0x0011:
            timestamp, x, y, z, flags, address, angle_word, time_shift = POSITION_MM.unpack(payload)
            per_m = MM_PER_M
        else:
            timestamp, x, y, z, flags, address, angle_word, time_shift = POSITION_MM64.unpack_from(payload)
            per_m = MM_PER_M
            velocity = _speed_extension(payload, POSITION_MM64.size)
        if flags & FLAG_OTHER_HEDGEHOG:
            self.counters.other_address += 1
            return None
        if self.hedgehog_address is None:
            self.hedgehog_address = address  # auto: the first frame the sender says is its own
            if self.previous_address not in (None, address):
                self.counters.address_changes += 1
        elif address != self.hedgehog_address and not self._relatches(address, arrival):
            self.counters.other_address += 1
            return None
        self._heard_at, self._candidate = arrival, (-1, 0)
        if self._is_duplicate("position", timestamp):
            return None
        timestamp_s = timestamp / (MS_PER_S if flags & FLAG_TIMESTAMP_MS else TICKS_PER_S_OLD)
        if flags & FLAG_UNAVAILABLE:
            self.counters.unavailable_fixes += 1
            return FixUnavailable(arrival, address, timestamp, timestamp_s, flags, code)
        return Position(
            arrival=arrival,
            t_meas=self._t_meas(arrival, time_shift),
            x=x / per_m,
            y=y / per_m,
            z=z / per_m,
            address=address,
            timestamp=timestamp,
            timestamp_s=timestamp_s,
            flags=flags,
            angle_word=angle_word,
            time_shift_s=time_shift / MS_PER_S,
            code=code,
            velocity=velocity,
        )

    def _beacons(self, code: int, payload: bytes, arrival: float) -> Event | None:
        layout, per_m = (BEACON_CM, CM_PER_M) if code == 0x0002 else (BEACON_MM, MM_PER_M)
        beacons = []
        for offset in range(1, len(payload), layout.size):
            if code == 0x0002:
                address, x, y, z = layout.unpack_from(payload, offset)
                applicable = True
            else:
                address, x, y, z, flags = layout.unpack_from(payload, offset)
                applicable = not flags & ITEM_NA
            beacons.append(StationaryBeacon(address, x / per_m, y / per_m, z / per_m, applicable))
        return StationaryBeacons(arrival, tuple(beacons), code)

    def _raw_imu(self, code: int, payload: bytes, arrival: float) -> Event | None:
        ax, ay, az, gx, gy, gz, mx, my, mz, address, timestamp, flags = (
            RAW_IMU if code == 0x0003 else RAW_IMU64
        ).unpack(payload)
        if not self._is_ours(address) or self._is_duplicate("raw_imu", timestamp):
            return None
        return RawImu(
            arrival=arrival,
            address=address,
            timestamp=timestamp,
            timestamp_s=timestamp / MS_PER_S,
            acceleration=None if flags & IMU_ACCEL_NA else (ax * ACCEL_LSB, ay * ACCEL_LSB, az * ACCEL_LSB),
            angular_velocity=None if flags & IMU_GYRO_NA else (gx * GYRO_LSB, gy * GYRO_LSB, gz * GYRO_LSB),
            magnetic_field=(
                None if flags & IMU_COMPASS_NA else (mx * COMPASS_XY_LSB, my * COMPASS_XY_LSB, mz * COMPASS_Z_LSB)
            ),
            flags=flags,
            code=code,
        )

    def _raw_distances(self, code: int, payload: bytes, arrival: float) -> Event | None:
        address, *fields = (RAW_DISTANCES if code == 0x0004 else RAW_DISTANCES64).unpack(payload)
        timestamp, time_shift = fields[12], fields[13]
        if not self._is_ours(address) or self._is_duplicate("raw_distances", timestamp):
            return None
        distances = tuple(
            Distance(beacon, millimetres / MM_PER_M, not item_flags & ITEM_NA)
            for beacon, millimetres, item_flags in zip(fields[0:12:3], fields[1:12:3], fields[2:12:3], strict=True)
            if beacon != 0  # address 0 marks an empty item
        )
        return RawDistances(
            arrival=arrival,
            t_meas=self._t_meas(arrival, time_shift),
            address=address,
            timestamp=timestamp,
            timestamp_s=timestamp / MS_PER_S,
            time_shift_s=time_shift / MS_PER_S,
            distances=distances,
            code=code,
        )

    def _imu_fusion(self, code: int, payload: bytes, arrival: float) -> Event | None:
        x, y, z, qw, qx, qy, qz, vx, vy, vz, ax, ay, az, address, timestamp, flags = (
            IMU_FUSION if code == 0x0005 else IMU_FUSION64
        ).unpack(payload)
        if not self._is_ours(address) or self._is_duplicate("imu_fusion", timestamp):
            return None
        q = QUATERNION_LSB
        return ImuFusion(
            arrival=arrival,
            address=address,
            timestamp=timestamp,
            timestamp_s=timestamp / MS_PER_S,
            position=None if flags & FUSION_POSITION_NA else (x / MM_PER_M, y / MM_PER_M, z / MM_PER_M),
            quaternion=None if flags & FUSION_QUATERNION_NA else (qw * q, qx * q, qy * q, qz * q),
            velocity=None if flags & FUSION_VELOCITY_NA else (vx / MM_PER_M, vy / MM_PER_M, vz / MM_PER_M),
            acceleration=None if flags & FUSION_ACCEL_NA else (ax / MM_PER_M, ay / MM_PER_M, az / MM_PER_M),
            flags=flags,
            code=code,
        )

    def _telemetry(self, code: int, payload: bytes, arrival: float) -> Event | None:
        battery_mv, rssi_dbm, address = TELEMETRY.unpack(payload)
        if not self._is_ours(address):
            return None
        return Telemetry(arrival, address, battery_mv * BATTERY_LSB, rssi_dbm, code)

    def _quality(self, code: int, payload: bytes, arrival: float) -> Event | None:
        address, quality_percent, geofence_zone = QUALITY.unpack(payload)
        if not self._is_ours(address):
            return None
        return Quality(arrival, address, quality_percent, geofence_zone, code)


def _speed_extension(payload: bytes, offset: int) -> tuple[float, float, float] | None:
    """The velocity of 0x0081's extension records (m/s), if present; an unknown subcode ends the records."""
    velocity = None
    while offset < len(payload) and payload[offset] == SUBCODE_SPEED and offset + SPEED_RECORD.size <= len(payload):
        _, vx, vy, vz = SPEED_RECORD.unpack_from(payload, offset)
        velocity = (vx / MM_PER_M, vy / MM_PER_M, vz / MM_PER_M)
        offset += SPEED_RECORD.size
    return velocity
