"""What the drivers read from their settings, as protocols: any object with these attributes will do.

Drivers take plain arguments and import nothing of robotd (as gpiozero devices take pin numbers); robotd's frozen
config sections satisfy these protocols structurally, and a test or another program can pass its own objects.
"""

from __future__ import annotations

from typing import Literal, Protocol, TypeVar


class PigpiodAddress(Protocol):
    """Where pigpiod listens, and how patiently to reach it."""

    @property
    def host(self) -> str: ...
    @property
    def port(self) -> int: ...
    @property
    def connect_timeout_s(self) -> float: ...
    @property
    def reconnect_max_s(self) -> float: ...


class EncoderPinsLike(Protocol):
    """One wheel's quadrature encoder: channel A and B pins and the sign of forward counting."""

    @property
    def a(self) -> int: ...
    @property
    def b(self) -> int: ...
    @property
    def sign(self) -> int: ...


class MotorPinsLike(Protocol):
    """One L298 channel: enable (PWM) pin, the two direction inputs, and the sign of forward duty."""

    @property
    def enable(self) -> int: ...
    @property
    def in1(self) -> int: ...
    @property
    def in2(self) -> int: ...
    @property
    def sign(self) -> int: ...


class EncoderSettings(Protocol):
    """The encoders: decoding, glitch filter, publish rate, pulls and the wheels' pins."""

    @property
    def counts_per_rev(self) -> int: ...
    @property
    def decoding(self) -> Literal["x1", "x2", "x4"]: ...
    @property
    def glitch_filter_us(self) -> int: ...
    @property
    def publish_rate_hz(self) -> float: ...
    @property
    def pull(self) -> Literal["up", "down", "off"]: ...
    @property
    def wheels(self) -> FourWheels[EncoderPinsLike]: ...


class MotorSettings(Protocol):
    """The motors: PWM frequency, duty limit and the wheels' pins."""

    @property
    def pwm_frequency_hz(self) -> int: ...
    @property
    def duty_limit(self) -> float: ...
    @property
    def wheels(self) -> FourWheels[MotorPinsLike]: ...


class MarvelmindSettings(Protocol):
    """The hedgehog's serial device and how its frames are taken."""

    @property
    def device(self) -> str: ...
    @property
    def baudrate(self) -> int: ...
    @property
    def hedgehog_address(self) -> int | Literal["auto"]: ...
    @property
    def default_latency_s(self) -> float: ...
    @property
    def stale_after_s(self) -> float: ...
    @property
    def reconnect_max_s(self) -> float: ...
    @property
    def relatch_after_s(self) -> float: ...
    @property
    def map_bounds_m(self) -> tuple[float, ...]: ...
    @property
    def map_margin_m(self) -> float: ...


T_co = TypeVar("T_co", covariant=True)


class FourWheels(Protocol[T_co]):
    """Something held per wheel."""

    @property
    def front_left(self) -> T_co: ...
    @property
    def front_right(self) -> T_co: ...
    @property
    def rear_left(self) -> T_co: ...
    @property
    def rear_right(self) -> T_co: ...


def in_wheel_order(wheels: FourWheels[T_co]) -> list[T_co]:
    """The four wheels' items in robotd's wheel order: front-left, front-right, rear-left, rear-right."""
    return [wheels.front_left, wheels.front_right, wheels.rear_left, wheels.rear_right]
