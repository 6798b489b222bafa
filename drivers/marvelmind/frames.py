"""Encoders of Marvelmind streaming frames, one per code: SI values in, a complete frame (CRC included) out.

Used by the virtual Marvelmind and by the tests. Values are rounded to the code's resolution; a value that does not
fit its field raises ValueError naming the code. Parsing an encoded frame gives back the values, and
`encode_event(event)` rebuilds the exact frame a parsed event came from (reserved bytes are zero).

Position timestamps are the beacon's raw counter: milliseconds when flags bit 1 is set (the default 0x02), else
1/64 s, as the 2016 firmware sends them.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence

from drivers.marvelmind.crc import crc16_modbus
from drivers.marvelmind.events import (
    Distance,
    Event,
    FixUnavailable,
    ImuFusion,
    Position,
    RawDistances,
    RawImu,
    StationaryBeacon,
    StationaryBeacons,
    Telemetry,
    Vector3,
)
from drivers.marvelmind.framing import HEADER
from drivers.marvelmind.protocol import (
    ACCEL_LSB,
    BATTERY_LSB,
    BEACON_CM,
    BEACON_MM,
    CM_PER_M,
    COMPASS_XY_LSB,
    COMPASS_Z_LSB,
    FUSION_ACCEL_NA,
    FUSION_POSITION_NA,
    FUSION_QUATERNION_NA,
    FUSION_VELOCITY_NA,
    GYRO_LSB,
    IMU_ACCEL_NA,
    IMU_COMPASS_NA,
    IMU_FUSION,
    IMU_FUSION64,
    IMU_GYRO_NA,
    ITEM_NA,
    MM_PER_M,
    MS_PER_S,
    POSITION_CM,
    POSITION_MM,
    POSITION_MM64,
    QUALITY,
    QUATERNION_LSB,
    RAW_DISTANCES,
    RAW_DISTANCES64,
    RAW_IMU,
    RAW_IMU64,
    SPEED_RECORD,
    SUBCODE_SPEED,
    TELEMETRY,
)

_ZERO3 = (0.0, 0.0, 0.0)


def build_frame(code: int, payload: bytes) -> bytes:
    """A streaming frame around `payload`: header, code, size, payload, CRC-16/MODBUS low byte first."""
    if len(payload) > 255:
        raise ValueError(f"code 0x{code:04x}: payload of {len(payload)} bytes exceeds 255")
    body = HEADER + struct.pack("<HB", code, len(payload)) + payload
    return body + struct.pack("<H", crc16_modbus(body))


def _pack(code: int, layout: struct.Struct, *values: object) -> bytes:
    try:
        return layout.pack(*values)
    except struct.error as error:
        raise ValueError(f"code 0x{code:04x}: a value does not fit its field: {error}") from None


def _scaled(values: Sequence[float], lsb: float) -> list[int]:
    return [round(value / lsb) for value in values]


def _counts(values: Sequence[float], per_unit: float) -> list[int]:
    return [round(value * per_unit) for value in values]


def _position(
    code: int,
    layout: struct.Struct,
    per_m: float,
    *,
    timestamp_ms: int,
    xyz_m: Vector3,
    address: int,
    flags: int,
    time_shift_ms: int,
    angle_word: int,
) -> bytes:
    x, y, z = _counts(xyz_m, per_m)
    return _pack(code, layout, timestamp_ms, x, y, z, flags, address, angle_word, time_shift_ms)


def encode_position_cm(
    timestamp_ms: int,
    x_m: float,
    y_m: float,
    z_m: float,
    address: int,
    *,
    flags: int = 0x02,
    time_shift_ms: int = 0,
    angle_word: int = 0,
) -> bytes:
    """Code 0x0001: position in cm, u32 timestamp."""
    payload = _position(
        0x0001,
        POSITION_CM,
        CM_PER_M,
        timestamp_ms=timestamp_ms,
        xyz_m=(x_m, y_m, z_m),
        address=address,
        flags=flags,
        time_shift_ms=time_shift_ms,
        angle_word=angle_word,
    )
    return build_frame(0x0001, payload)


def encode_position_mm(
    timestamp_ms: int,
    x_m: float,
    y_m: float,
    z_m: float,
    address: int,
    *,
    flags: int = 0x02,
    time_shift_ms: int = 0,
    angle_word: int = 0,
) -> bytes:
    """Code 0x0011: position in mm, u32 timestamp."""
    payload = _position(
        0x0011,
        POSITION_MM,
        MM_PER_M,
        timestamp_ms=timestamp_ms,
        xyz_m=(x_m, y_m, z_m),
        address=address,
        flags=flags,
        time_shift_ms=time_shift_ms,
        angle_word=angle_word,
    )
    return build_frame(0x0011, payload)


def encode_position_mm64(
    timestamp_ms: int,
    x_m: float,
    y_m: float,
    z_m: float,
    address: int,
    *,
    flags: int = 0x02,
    time_shift_ms: int = 0,
    angle_word: int = 0,
    velocity_mps: Vector3 | None = None,
) -> bytes:
    """Code 0x0081: position in mm, i64 timestamp, with the speed extension record when a velocity is given."""
    payload = _position(
        0x0081,
        POSITION_MM64,
        MM_PER_M,
        timestamp_ms=timestamp_ms,
        xyz_m=(x_m, y_m, z_m),
        address=address,
        flags=flags,
        time_shift_ms=time_shift_ms,
        angle_word=angle_word,
    )
    if velocity_mps is not None:
        payload += _pack(0x0081, SPEED_RECORD, SUBCODE_SPEED, *_counts(velocity_mps, MM_PER_M))
    return build_frame(0x0081, payload)


def encode_beacons_cm(beacons: Sequence[StationaryBeacon]) -> bytes:
    """Code 0x0002: stationary beacon positions in cm (the `applicable` flag is not carried by this code)."""
    payload = bytes([len(beacons)]) + b"".join(
        _pack(0x0002, BEACON_CM, b.address, *_counts((b.x, b.y, b.z), CM_PER_M)) for b in beacons
    )
    return build_frame(0x0002, payload)


def encode_beacons_mm(beacons: Sequence[StationaryBeacon]) -> bytes:
    """Code 0x0012: stationary beacon positions in mm with their "not applicable" flag."""
    payload = bytes([len(beacons)]) + b"".join(
        _pack(0x0012, BEACON_MM, b.address, *_counts((b.x, b.y, b.z), MM_PER_M), 0 if b.applicable else ITEM_NA)
        for b in beacons
    )
    return build_frame(0x0012, payload)


def _raw_imu(
    code: int,
    timestamp_ms: int,
    address: int,
    *,
    acceleration: Vector3 | None,
    angular_velocity: Vector3 | None,
    magnetic_field: Vector3 | None,
    flags: int,
) -> bytes:
    flags |= (IMU_ACCEL_NA if acceleration is None else 0) | (IMU_GYRO_NA if angular_velocity is None else 0)
    flags |= IMU_COMPASS_NA if magnetic_field is None else 0
    mx, my, mz = magnetic_field or _ZERO3
    values = [
        *_scaled(acceleration or _ZERO3, ACCEL_LSB),
        *_scaled(angular_velocity or _ZERO3, GYRO_LSB),
        round(mx / COMPASS_XY_LSB),
        round(my / COMPASS_XY_LSB),
        round(mz / COMPASS_Z_LSB),
    ]
    layout = RAW_IMU if code == 0x0003 else RAW_IMU64
    return build_frame(code, _pack(code, layout, *values, address, timestamp_ms, flags))


def encode_raw_imu(
    timestamp_ms: int,
    address: int,
    *,
    acceleration: Vector3 | None = None,
    angular_velocity: Vector3 | None = None,
    magnetic_field: Vector3 | None = None,
    flags: int = 0,
) -> bytes:
    """Code 0x0003: raw IMU (m/s^2, rad/s, T); a sensor given as None is flagged not available."""
    return _raw_imu(
        0x0003,
        timestamp_ms,
        address,
        acceleration=acceleration,
        angular_velocity=angular_velocity,
        magnetic_field=magnetic_field,
        flags=flags,
    )


def encode_raw_imu64(
    timestamp_ms: int,
    address: int,
    *,
    acceleration: Vector3 | None = None,
    angular_velocity: Vector3 | None = None,
    magnetic_field: Vector3 | None = None,
    flags: int = 0,
) -> bytes:
    """Code 0x0083: raw IMU with an i64 timestamp."""
    return _raw_imu(
        0x0083,
        timestamp_ms,
        address,
        acceleration=acceleration,
        angular_velocity=angular_velocity,
        magnetic_field=magnetic_field,
        flags=flags,
    )


def _raw_distances(
    code: int, timestamp_ms: int, address: int, distances: Sequence[Distance], time_shift_ms: int
) -> bytes:
    if len(distances) > 4:
        raise ValueError(f"code 0x{code:04x}: at most 4 distances, got {len(distances)}")
    if any(item.beacon == 0 for item in distances):
        raise ValueError(f"code 0x{code:04x}: beacon address 0 marks an empty item")
    items: list[int] = []
    for item in distances:
        items += [item.beacon, round(item.distance * MM_PER_M), 0 if item.valid else ITEM_NA]
    items += [0, 0, 0] * (4 - len(distances))
    layout = RAW_DISTANCES if code == 0x0004 else RAW_DISTANCES64
    return build_frame(code, _pack(code, layout, address, *items, timestamp_ms, time_shift_ms))


def encode_raw_distances(
    timestamp_ms: int, address: int, distances: Sequence[Distance], time_shift_ms: int = 0
) -> bytes:
    """Code 0x0004: up to four hedgehog-to-beacon distances (m)."""
    return _raw_distances(0x0004, timestamp_ms, address, distances, time_shift_ms)


def encode_raw_distances64(
    timestamp_ms: int, address: int, distances: Sequence[Distance], time_shift_ms: int = 0
) -> bytes:
    """Code 0x0084: raw distances with an i64 timestamp."""
    return _raw_distances(0x0084, timestamp_ms, address, distances, time_shift_ms)


def _imu_fusion(
    code: int,
    timestamp_ms: int,
    address: int,
    *,
    position: Vector3 | None,
    quaternion: tuple[float, float, float, float] | None,
    velocity: Vector3 | None,
    acceleration: Vector3 | None,
    flags: int,
) -> bytes:
    flags |= (FUSION_POSITION_NA if position is None else 0) | (FUSION_QUATERNION_NA if quaternion is None else 0)
    flags |= (FUSION_VELOCITY_NA if velocity is None else 0) | (FUSION_ACCEL_NA if acceleration is None else 0)
    values = [
        *_counts(position or _ZERO3, MM_PER_M),
        *_scaled(quaternion or (0.0, 0.0, 0.0, 0.0), QUATERNION_LSB),
        *_counts(velocity or _ZERO3, MM_PER_M),
        *_counts(acceleration or _ZERO3, MM_PER_M),
    ]
    layout = IMU_FUSION if code == 0x0005 else IMU_FUSION64
    return build_frame(code, _pack(code, layout, *values, address, timestamp_ms, flags))


def encode_imu_fusion(
    timestamp_ms: int,
    address: int,
    *,
    position: Vector3 | None = None,
    quaternion: tuple[float, float, float, float] | None = None,
    velocity: Vector3 | None = None,
    acceleration: Vector3 | None = None,
    flags: int = 0,
) -> bytes:
    """Code 0x0005: IMU fusion (m, unit quaternion w x y z, m/s, m/s^2); a part given as None is flagged n/a."""
    return _imu_fusion(
        0x0005,
        timestamp_ms,
        address,
        position=position,
        quaternion=quaternion,
        velocity=velocity,
        acceleration=acceleration,
        flags=flags,
    )


def encode_imu_fusion64(
    timestamp_ms: int,
    address: int,
    *,
    position: Vector3 | None = None,
    quaternion: tuple[float, float, float, float] | None = None,
    velocity: Vector3 | None = None,
    acceleration: Vector3 | None = None,
    flags: int = 0,
) -> bytes:
    """Code 0x0085: IMU fusion with an i64 timestamp."""
    return _imu_fusion(
        0x0085,
        timestamp_ms,
        address,
        position=position,
        quaternion=quaternion,
        velocity=velocity,
        acceleration=acceleration,
        flags=flags,
    )


def encode_telemetry(address: int, battery_v: float, rssi_dbm: int) -> bytes:
    """Code 0x0006: battery voltage (V) and radio RSSI (dBm)."""
    return build_frame(0x0006, _pack(0x0006, TELEMETRY, round(battery_v / BATTERY_LSB), rssi_dbm, address))


def encode_quality(address: int, quality_percent: int, geofence_zone: int = 0) -> bytes:
    """Code 0x0007: positioning quality (%) and geofence alarm zone (0 = none)."""
    return build_frame(0x0007, _pack(0x0007, QUALITY, address, quality_percent, geofence_zone))


_POSITION_ENCODERS = {0x0001: encode_position_cm, 0x0011: encode_position_mm}


def encode_event(event: Event) -> bytes:
    """The frame an event was parsed from (a FixUnavailable's discarded coordinates are encoded as 0)."""
    if isinstance(event, Position):
        args = (event.timestamp, event.x, event.y, event.z, event.address)
        shift_ms = round(event.time_shift_s * MS_PER_S)
        if event.code == 0x0081:
            return encode_position_mm64(
                *args,
                flags=event.flags,
                time_shift_ms=shift_ms,
                angle_word=event.angle_word,
                velocity_mps=event.velocity,
            )
        return _POSITION_ENCODERS[event.code](
            *args, flags=event.flags, time_shift_ms=shift_ms, angle_word=event.angle_word
        )
    if isinstance(event, FixUnavailable):
        encoder = encode_position_mm64 if event.code == 0x0081 else _POSITION_ENCODERS[event.code]
        return encoder(event.timestamp, 0.0, 0.0, 0.0, event.address, flags=event.flags)
    if isinstance(event, StationaryBeacons):
        return (encode_beacons_cm if event.code == 0x0002 else encode_beacons_mm)(event.beacons)
    if isinstance(event, RawImu):
        return _raw_imu(
            event.code,
            event.timestamp,
            event.address,
            acceleration=event.acceleration,
            angular_velocity=event.angular_velocity,
            magnetic_field=event.magnetic_field,
            flags=event.flags,
        )
    if isinstance(event, RawDistances):
        shift_ms = round(event.time_shift_s * MS_PER_S)
        return _raw_distances(event.code, event.timestamp, event.address, event.distances, shift_ms)
    if isinstance(event, ImuFusion):
        return _imu_fusion(
            event.code,
            event.timestamp,
            event.address,
            position=event.position,
            quaternion=event.quaternion,
            velocity=event.velocity,
            acceleration=event.acceleration,
            flags=event.flags,
        )
    if isinstance(event, Telemetry):
        return encode_telemetry(event.address, event.battery_v, event.rssi_dbm)
    return encode_quality(event.address, event.quality_percent, event.geofence_zone)
