"""robotd's configuration: YAML in, frozen dataclasses out, validated once at start-up.

Each section is a frozen dataclass; `load()` reports every problem at once by dotted path (see `robotd.config.schema`).
Units are in the key names (`_m`, `_s`, `_hz`, `_rad`); everything inside robotd is SI.
Wheel order everywhere: front_left, front_right, rear_left, rear_right (the paper's w1..w4).
"""

from __future__ import annotations

import dataclasses
import ipaddress
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from robotd.config.fleet import FleetConfig
from robotd.config.gpio import GpioConfig, gpiod_problems
from robotd.config.schema import (
    ConfigError,
    build,
    each,
    file_mode,
    gpio_pin,
    host,
    in_range,
    ip_address,
    non_negative,
    port_number,
    positive,
    reference,
    section,
    setting,
)
from robotd.config.sim import SimConfig
from robotd.config.smallfile import MissingFileError, SmallFileError, read_small_file
from robotd.config.viewer import ViewerConfig
from robotd.config.yamltext import parse_yaml

WHEELS = ("front_left", "front_right", "rear_left", "rear_right")
MAX_CONFIG_BYTES = 1 << 20  # robot.yaml is 4 kB; a bound keeps a wrong path (a log, a device) from being read whole


def _sign(value: int) -> str | None:
    """+1 or -1."""
    return None if value in (1, -1) else f"must be 1 or -1, got {value!r}"


@dataclass(frozen=True, slots=True)
class RobotConfig:
    """Geometry of the mecanum robot (paper section III)."""

    wheel_radius_m: float = setting(0.046875, "Wheel radius r (paper: 46.875 mm).", positive)
    lx_m: float = setting(0.135, "Half the front-rear wheel distance (paper's lfr: 135 mm).", positive)
    ly_m: float = setting(0.125, "Half the left-right wheel distance (paper's lrl: 125 mm).", positive)
    ips_offset_m: tuple[float, float] = setting(
        (0.0, 0.0), "Position of the Marvelmind beacon in the body frame (x forward, y left): its lever arm."
    )


@dataclass(frozen=True, slots=True)
class EncoderPins:
    """One wheel's quadrature encoder."""

    a: int = setting(4, "BCM GPIO of channel A.", gpio_pin)
    b: int = setting(17, "BCM GPIO of channel B.", gpio_pin)
    sign: int = setting(1, "+1 if counting up means the wheel turns forward, else -1.", _sign)


@dataclass(frozen=True, slots=True)
class EncoderWheels:
    """Encoder pins per wheel (defaults: the Pi 4 wiring documented in config/robot.yaml)."""

    front_left: EncoderPins = section(lambda: EncoderPins(4, 17, 1), "Front-left wheel (w1).")
    front_right: EncoderPins = section(lambda: EncoderPins(27, 22, 1), "Front-right wheel (w2).")
    rear_left: EncoderPins = section(lambda: EncoderPins(5, 6, 1), "Rear-left wheel (w3).")
    rear_right: EncoderPins = section(lambda: EncoderPins(2, 3, 1), "Rear-right wheel (w4).")


@dataclass(frozen=True, slots=True)
class EncodersConfig:
    """Quadrature encoders read through pigpiod's notification stream."""

    ppr: int = setting(1700, "Pulses per revolution of one channel, at the wheel.", positive)
    decoding: Literal["x1", "x2", "x4"] = setting(
        "x4", "Edges counted per pulse: x1, x2 or x4 (x4 = 4 * ppr counts a turn)."
    )
    glitch_filter_us: int = setting(
        5,
        "pigpio glitch filter: a level must be steady this long (us) to be reported; 0 disables it.",
        in_range(0, 300_000),
    )
    publish_rate_hz: float = setting(
        50.0,
        "Rate at which decoded wheel ticks and speeds are handed to the estimator and the wheel-speed control (which"
        " runs at control.rate_hz: faster costs CPU for speeds it does not read). Speeds are edge-timed: exact as of"
        " the last edge, whatever the rate.",
        in_range(1.0, 2000.0),
    )
    pull: Literal["up", "down", "off"] = setting(
        "up", "Pull resistor of the encoder inputs: up for open-collector encoders, off for push-pull ones."
    )
    wheels: EncoderWheels = section(EncoderWheels, "Pins and direction per wheel.")

    @property
    def counts_per_rev(self) -> int:
        """Counts per wheel turn after decoding."""
        return self.ppr * {"x1": 1, "x2": 2, "x4": 4}[self.decoding]


@dataclass(frozen=True, slots=True)
class MotorPins:
    """One L298 channel: enable (PWM) and the two direction inputs."""

    enable: int = setting(12, "BCM GPIO of the L298 enable input (PWM).", gpio_pin)
    in1: int = setting(16, "BCM GPIO of the first direction input (high = forward).", gpio_pin)
    in2: int = setting(20, "BCM GPIO of the second direction input (high = backward).", gpio_pin)
    sign: int = setting(1, "+1 if a positive duty turns the wheel forward, else -1.", _sign)


@dataclass(frozen=True, slots=True)
class MotorWheels:
    """Motor pins per wheel."""

    front_left: MotorPins = section(lambda: MotorPins(12, 16, 20, 1), "Front-left wheel (w1).")
    front_right: MotorPins = section(lambda: MotorPins(13, 21, 26, 1), "Front-right wheel (w2).")
    rear_left: MotorPins = section(lambda: MotorPins(18, 23, 24, 1), "Rear-left wheel (w3).")
    rear_right: MotorPins = section(lambda: MotorPins(19, 25, 11, 1), "Rear-right wheel (w4).")


@dataclass(frozen=True, slots=True)
class MotorsConfig:
    """L298 motor drivers through gpiozero on pigpiod."""

    pwm_frequency_hz: int = setting(1000, "PWM frequency of the enable pins.", in_range(10, 40_000))
    duty_limit: float = setting(1.0, "Largest duty magnitude ever sent to a motor, in (0, 1].", in_range(0.01, 1.0))
    deadman_script: bool = setting(
        True,
        "Run a deadman script inside pigpiod that drives every motor pin low when robotd stops refreshing it for "
        "teleop.deadman_timeout_s (killed, stopped or hung): the wheels stop within that time plus one control "
        "period, whatever happened to robotd.",
    )
    wheels: MotorWheels = section(MotorWheels, "Pins and direction per wheel.")


@dataclass(frozen=True, slots=True)
class PigpiodConfig:
    """The pigpio daemon (real on the Pi, virtual in simulation)."""

    host: str = setting("127.0.0.1", "Host of pigpiod (keep it on localhost: pigpiod has no authentication).", host)
    port: int = setting(8888, "TCP port of pigpiod.", port_number)
    connect_timeout_s: float = setting(
        2.0,
        "Give up one connection attempt after this long; at most 5 s, so `robotd stop-motors` finishes well within"
        " systemd's stop timeout (10 s).",
        in_range(0.0, 5.0, above_low=True),
    )
    reconnect_max_s: float = setting(
        5.0,
        "Longest wait between reconnection attempts (backoff cap); at most 30 s: the motors cannot be driven or"
        " stopped by robotd while pigpiod is away.",
        in_range(0.0, 30.0, above_low=True),
    )


def _device_pattern(value: str) -> str | None:
    """Must not be empty."""
    return None if value.strip() else "must name a serial device (a path or a glob), got an empty string"


def _map_bounds(value: tuple[float, ...]) -> str | None:
    """Empty, or [xmin, ymin, xmax, ymax] with xmin < xmax and ymin < ymax."""
    if not value or any(v is None for v in value):  # (None: an element already reported as not a number)
        return None
    if len(value) != 4:
        return f"must be empty or [xmin, ymin, xmax, ymax], got {len(value)} numbers"
    xmin, ymin, xmax, ymax = value
    return None if xmin < xmax and ymin < ymax else f"needs xmin < xmax and ymin < ymax, got {list(value)}"


@dataclass(frozen=True, slots=True)
class MarvelmindConfig:
    """The Marvelmind hedgehog on a serial port."""

    device: str = setting(
        "/dev/marvelmind",
        "Serial device: a path, a /dev/serial/by-id/... path or a glob (first sorted match, resolved on every "
        "reconnection). robotd only reads it: any write stops the beacon's stream for 5 s.",
        _device_pattern,
    )
    baudrate: int = setting(500000, "UART baud rate (ignored over USB).", in_range(4800, 500000))
    hedgehog_address: int | Literal["auto"] = setting(
        "auto",
        "Address of our hedgehog, 0..255, or auto to learn it from the first position frame not flagged as "
        "another hedgehog's (flags bit 6). Frames of other addresses are dropped.",
    )
    stale_after_s: float = setting(
        0.3,
        "A fix is stale after this long without a valid one; at most 5 s: an older fix no longer says where a"
        " moving robot is.",
        in_range(0.0, 5.0, above_low=True),
    )
    default_latency_s: float = setting(
        0.05, "Latency assumed when a frame's time-shift field is 0 (unknown).", in_range(0.0, 5.0)
    )
    reconnect_max_s: float = setting(
        2.0,
        "Longest wait between attempts to reopen a vanished device; at most 30 s (the pose runs on odometry alone"
        " meanwhile).",
        in_range(0.0, 30.0, above_low=True),
    )
    relatch_after_s: float = setting(
        2.0,
        "With hedgehog_address auto: follow another address once ours has sent no position for this long while the "
        "other streams (a hedgehog swapped behind a port that stayed open). A reopened port always learns the "
        "address again from its first position frame.",
        in_range(0.1, 3600.0),
    )
    map_bounds_m: tuple[float, ...] = setting(
        (),
        "[xmin, ymin, xmax, ymax] of the map (m): fixes outside are refused and counted (outside_map), never fused. "
        "Empty: the stationary beacons' bounding box grown by map_margin_m, once the hedgehog reports the beacons.",
        _map_bounds,
    )
    map_margin_m: float = setting(
        3.0,
        "Margin around the stationary beacons' bounding box (codes 0x0002, 0x0012) beyond which fixes are refused, "
        "when map_bounds_m is empty.",
        in_range(0.0, 1000.0),
    )

    def __post_init__(self) -> None:
        if isinstance(self.hedgehog_address, int) and not 0 <= self.hedgehog_address <= 255:
            raise ValueError(f"hedgehog_address must be between 0 and 255, got {self.hedgehog_address}")


@dataclass(frozen=True, slots=True)
class EkfConfig:
    """The Extended Kalman Filter fusing odometry with IPS fixes (robotd/ekf.py, robotd/estimator.py).

    Odometry noise is a random walk that grows with distance travelled and angle turned, never with time alone:
    a robot at rest does not grow uncertain. The `paper_*` keys are used only by the paper's filter as published
    (`paper_preset`).
    """

    initial_pose: tuple[float, float, float] = setting((0.0, 0.0, 0.0), "Initial x (m), y (m), theta (rad).")
    initial_sigma: tuple[float, float, float] = setting(
        (1.0, 1.0, 3.14),
        "Initial standard deviation of x (m), y (m), theta (rad). A theta above 0.5 rad means the heading is unknown:"
        " the position then follows the fixes until a whole heading_align_m of driving gives the heading. Set it"
        " small (0.1) only when the robot always starts facing initial_pose's theta.",
        each(positive),
    )
    unknown_heading_sigma_rad: float = setting(
        0.5, "An initial_sigma theta above this means the heading is unknown until driving gives it.", positive
    )
    seed_fixes: int = setting(
        3,
        "Fixes that must agree with each other to place the position at start (a first fix may be an outlier); 0:"
        " the initial pose is trusted and fixes are judged from the first.",
        in_range(0, 100),
    )
    ips_sigma_m: float = setting(
        0.03,
        "Standard deviation of one IPS fix in x and y (paper's s_ips): the prior of the learnt noise, and the least"
        " noise the gate judges a fix with.",
        positive,
    )
    gating: bool = setting(
        True,
        "Reject fixes whose Mahalanobis distance exceeds the chi-square gate (judged with the fix noise learnt or"
        " ips_sigma_m, whichever is larger).",
    )
    gate_probability: float = setting(
        0.999,
        "Chi-square (2 dof) probability of the gate: fixes beyond it are rejected.",
        in_range(0.5, 0.999999),
    )
    confirm_far_fixes: bool = setting(
        True,
        "A fix inside the gate only because the position is uncertain (it would fail the gate were the prediction as"
        " good as a fix) is fused once the next fix agrees with it: a gate that wide cannot tell it from an outlier.",
    )
    odom_along_sigma_m: float = setting(
        0.02, "Odometry position error along the body x axis, std per sqrt(metre travelled).", non_negative
    )
    odom_across_sigma_m: float = setting(
        0.03,
        "Odometry position error along the body y axis (mecanum rollers slip sideways), std per sqrt(metre).",
        non_negative,
    )
    slip_heading_sigma_rad: float = setting(
        0.05,
        "Heading drift from unequal wheel traction on an uneven floor, std (rad) per sqrt(metre travelled).",
        non_negative,
    )
    turn_heading_sigma_rad: float = setting(
        0.05, "Heading error from turning (wheel scrub), std (rad) per sqrt(radian turned).", non_negative
    )
    odom_turn_sigma_m: float = setting(
        0.003,
        "Odometry position error from turning, std per axis (m) per sqrt(radian turned): wheels of unequal traction"
        " move the centre of a robot turning on the spot, which its odometry reads as no motion at all.",
        non_negative,
    )
    predict_period_s: float = setting(
        0.05,
        "Wheel ticks are integrated into one prediction at most this often (0: every sample); the body "
        "displacement is exact either way, the midpoint heading keeps turns exact to second order.",
        in_range(0.0, 0.5),
    )
    midpoint_heading: bool = setting(
        True, "Move each prediction step along its midpoint heading (false: the heading at its start, Euler's step)."
    )
    step_sigma_v_mps: float = setting(
        0.0, "Speed noise std per prediction step on vx and vy, whatever the motion (the paper's eq. 9).", non_negative
    )
    step_sigma_w_rad_s: float = setting(
        0.0, "Turn-rate noise std per prediction step, whatever the motion (the paper's eq. 9).", non_negative
    )
    lever_arm: bool = setting(True, "Model the beacon's lever arm (robot.ips_offset_m): the fix depends on theta.")
    latency_compensation: bool = setting(
        True, "Fuse each fix at its measurement time, from the state the filter had then (kept as a short history)."
    )
    history_s: float = setting(
        1.0,
        "Length of that history: fixes measured earlier than this before the newest input are dropped.",
        in_range(0.0, 10.0),
    )
    adaptive_ips_noise: bool = setting(
        True,
        "Estimate the IPS noise from the median of recent innovations (robust to outliers), never above "
        "ips_sigma_max_m, nor below ips_sigma_m until the fixes have been judged (the first window of driving tells "
        "whether their errors persist from fix to fix), nor below ips_sigma_min_m after (nor, for fixes whose errors "
        "persist, below the noise the judging fit saw).",
    )
    ips_sigma_max_m: float = setting(0.3, "Largest IPS noise the adaptive estimate may reach.", positive)
    ips_sigma_min_m: float = setting(
        0.005,
        "Smallest IPS noise the adaptive estimate may reach once the fixes have been judged: an IPS quieter than "
        "configured is then trusted for what it is.",
        positive,
    )
    adaptive_process_noise: bool = setting(
        True,
        "Scale the odometry noise (odom_*_sigma_m, *_heading_sigma_rad, which are then the prior) by the factors, one"
        " on the position terms and one on the heading terms, that make the fixes likeliest (a bank of shadow filters,"
        " one per candidate), each within [process_noise_scale_min, process_noise_scale_max], while the fixes are "
        "judged independent: a flat floor earns a filter that averages more fixes, and a covariance that says so.",
    )
    process_noise_scale_min: float = setting(
        0.01,
        "Smallest factor a learnt scale may put on the odometry noise variances (a flat floor's odometry drifts a "
        "hundredth of the default noise or less).",
        in_range(0.01, 1.0),
    )
    process_noise_scale_max: float = setting(
        4.0, "Largest factor a learnt scale may put on the odometry noise variances.", in_range(1.0, 100.0)
    )
    recovery_min_s: float = setting(
        1.5,
        "Fixes rejected for at least this long that agree with each other re-seed the position (lock-out recovery); "
        "longer than any burst of consistent outliers.",
        in_range(0.1, 60.0),
    )
    recovery_min_fixes: int = setting(5, "Rejected fixes needed, at least, before such a recovery.", in_range(2, 1000))
    recovery_agreement_m: float = setting(
        0.2,
        "Rejected fixes agree when each lies within this distance (or 4 sigma of the IPS noise, if larger) of their "
        "median, after odometry motion is removed.",
        positive,
    )
    heading_align_m: float = setting(
        0.6,
        "After start-up and after a recovery, the heading is checked by aligning this much odometry track with the "
        "fixes (a rotation fit); 0 disables. Makes an unknown initial heading harmless.",
        non_negative,
    )
    heading_min_speed_mps: float = setting(
        0.02,
        "Below this speed a fix does not correct the heading: at rest a fix says nothing about it.",
        non_negative,
    )
    calibrate: bool = setting(
        True,
        "Learn from the fixes the odometry's scales (forward, sideways, rotation) and the delay of fixes that carry no"
        " measurement time, window by window of travel, bounded and slowly varying (robotd/estimation/calibration.py).",
    )
    odometry_scale: tuple[float, float, float] = setting(
        (1.0, 1.0, 1.0),
        "Starting multipliers of the odometry's vx, vy and wz (effective wheel radius over the configured one, and so"
        " on; `robotd tune` fits them). A calibration saved by the daemon (calibration_file) takes precedence.",
        each(in_range(0.5, 2.0)),
    )
    scale_sigma: float = setting(
        0.1,
        "Standard deviation of each starting odometry scale (how far from it calibration may look); half of its"
        " variance is the wheel radius's, which the three scales share.",
        positive,
    )
    scale_limit: float = setting(
        0.25, "Learnt odometry scales stay within 1 +- this.", in_range(0.0, 0.5, above_low=True)
    )
    latency_max_s: float = setting(
        0.5, "The learnt delay of fixes without a measurement time stays within [0, this].", in_range(0.0, 5.0)
    )
    calibration_window_m: float = setting(
        1.5,
        "Travel per calibration window (each window's odometry path is fitted to its fixes; it closes once it also"
        " holds 30 fixes).",
        in_range(0.2, 100.0),
    )
    calibration_file: str = setting(
        "",
        "Where the daemon keeps the learnt calibration across restarts (the unit's StateDirectory, e.g."
        " /var/lib/robotd/calibration.json); '' keeps it in memory only.",
    )
    paper_sigma_v_mps: float = setting(
        0.1, "Paper's filter: eq. 9's speed noise std, applied to vx and vy per prediction step.", non_negative
    )
    paper_sigma_w_rad_s: float = setting(
        0.2, "Paper's filter: eq. 9's turn-rate noise std per prediction step.", non_negative
    )


def paper_preset(ekf: EkfConfig) -> EkfConfig:
    """The paper's filter as published, from a configuration: every fix fused on arrival as it comes (no seeding, no
    gate, no latency compensation, no lever arm, R = ips_sigma_m^2 fixed), Euler steps with eq. 9's per-step noise
    (paper_sigma_*), the configured initial heading taken as known and never re-aligned."""
    return dataclasses.replace(
        ekf,
        unknown_heading_sigma_rad=math.inf,
        seed_fixes=0,
        gating=False,
        confirm_far_fixes=False,
        odom_along_sigma_m=0.0,
        odom_across_sigma_m=0.0,
        slip_heading_sigma_rad=0.0,
        turn_heading_sigma_rad=0.0,
        odom_turn_sigma_m=0.0,
        midpoint_heading=False,
        step_sigma_v_mps=ekf.paper_sigma_v_mps,
        step_sigma_w_rad_s=ekf.paper_sigma_w_rad_s,
        lever_arm=False,
        latency_compensation=False,
        adaptive_ips_noise=False,
        adaptive_process_noise=False,
        heading_align_m=0.0,
        heading_min_speed_mps=0.0,
        calibrate=False,
        odometry_scale=(1.0, 1.0, 1.0),
    )


def gated_preset(ekf: EkfConfig) -> EkfConfig:
    """A textbook EKF with the two fixes every practitioner adds, as a baseline: the paper's filter, but fixes beyond
    the chi-square gate are rejected, fixes are fused at their measurement time (untimed ones at the configured
    latency), and the position is placed from seed_fixes that agree (a gate alone would lock out a robot that starts
    away from initial_pose). No lever arm, learnt noise, calibration or heading alignment."""
    return dataclasses.replace(
        paper_preset(ekf),
        seed_fixes=ekf.seed_fixes,
        gating=True,
        gate_probability=ekf.gate_probability,
        latency_compensation=True,
    )


@dataclass(frozen=True, slots=True)
class TeleopConfig:
    """UDP teleop: authenticated body-frame velocity commands."""

    bind: str = setting("127.0.0.1", "Address to listen on (0.0.0.0 for a remote control on the network).", ip_address)
    port: int = setting(47800, "UDP port.", port_number)
    key_file: str = setting("/etc/robotd/teleop.key", "File holding the shared HMAC-SHA256 key.")
    allow_unauthenticated: bool = setting(False, "Accept datagrams without a key (loopback simulation only).")
    deadman_timeout_s: float = setting(
        0.5,
        "Stop the motors when no valid command arrived for this long; at most 5 s: a robot whose remote control is"
        " gone must not drive on for longer than a person takes to notice.",
        in_range(0.0, 5.0, above_low=True),
    )
    max_vx_mps: float = setting(
        0.6,
        "Largest forward speed magnitude; at most 3 m/s (an indoor robot: more is a typo).",
        in_range(0.0, 3.0, above_low=True),
    )
    max_vy_mps: float = setting(
        0.6, "Largest sideways speed magnitude; at most 3 m/s, as max_vx_mps.", in_range(0.0, 3.0, above_low=True)
    )
    max_wz_rad_s: float = setting(
        2.0,
        "Largest turn rate magnitude; at most 10 rad/s (more than a turn and a half a second).",
        in_range(0.0, 10.0, above_low=True),
    )
    max_linear_accel_mps2: float = setting(
        1.0,
        "Acceleration limit on vx and vy; at most 10 m/s^2 (1 g): the limit is what makes a stop gentle.",
        in_range(0.0, 10.0, above_low=True),
    )
    max_angular_accel_rad_s2: float = setting(
        4.0,
        "Acceleration limit on wz; at most 40 rad/s^2, as max_linear_accel_mps2.",
        in_range(0.0, 40.0, above_low=True),
    )
    max_datagram_age_s: float = setting(
        0.25,
        "Drop a datagram delayed this much more than the fastest one of its sender (clock offset estimated); at most"
        " 1 s: an older command is no longer what the operator means.",
        in_range(0.01, 1.0),
    )
    max_clock_offset_s: float = setting(
        5.0,
        "Drop a datagram whose sender clock (Unix time) differs from ours by more than this; above 0 and at most"
        " 60 s: a captured datagram can be replayed for this long (keep the clocks in sync with NTP).",
        in_range(0.0, 60.0, above_low=True),
    )
    max_datagrams_per_s: float = setting(
        200.0,
        "Datagrams taken per second from one source address (a token bucket holding a quarter second of them); more"
        " are dropped before any parsing and counted as rate_limited. A teleop client sends 20 to 50.",
        in_range(1.0, 1_000_000.0),
    )
    max_sources: int = setting(
        256,
        "Source addresses the rate limit remembers; the one seen least recently is forgotten first.",
        in_range(1, 100_000),
    )
    read_budget_per_s: float = setting(
        10_000.0,
        "Datagrams read from the socket per second, all sources together: beyond it reading pauses and the kernel"
        " drops the excess, so a flood costs the daemon a bounded share of the CPU and the control loop keeps time.",
        in_range(100.0, 10_000_000.0),
    )


@dataclass(frozen=True, slots=True)
class PoseSocketConfig:
    """The local pose stream: newline-delimited JSON on a Unix socket."""

    path: str = setting("/run/robotd/pose.sock", "Path of the Unix socket.")
    mode: str = setting("0660", "Permissions of the socket file (octal).", file_mode)
    rate_hz: float = setting(20.0, "Pose messages per second.", in_range(0.1, 1000.0))
    status_rate_hz: float = setting(
        1.0, "Status messages (driver counters, filter diagnostics) per second.", in_range(0.01, 100.0)
    )
    client_queue: int = setting(
        64,
        "Messages queued per client; a slow client loses the oldest. At most 10000: the queues of max_clients"
        " stuck clients must fit in the Pi's memory.",
        in_range(1, 10_000),
    )
    client_stall_s: float = setting(
        5.0,
        "Disconnect a client that has accepted no data for this long while messages wait; at most 60 s, so a stuck"
        " client soon frees its place and its queue.",
        in_range(0.0, 60.0, above_low=True),
    )
    max_clients: int = setting(
        16,
        "Most clients served at once; more are refused. At most 128 (each costs a queue and a task).",
        in_range(1, 128),
    )


@dataclass(frozen=True, slots=True)
class ControlConfig:
    """The motor control loop: wheel speed PID with feed-forward."""

    rate_hz: float = setting(
        50.0,
        "Control loop rate; at least 10 Hz (the deadman stops the wheels one control period after its timeout) and"
        " at most 1000 Hz (the Pi's CPU).",
        in_range(10.0, 1000.0),
    )
    kp: float = setting(
        0.02,
        "Proportional gain, duty per rad/s of wheel speed error; at most 1 (full duty for 1 rad/s of error already"
        " makes the wheel oscillate).",
        in_range(0.0, 1.0),
    )
    ki: float = setting(0.1, "Integral gain, duty per rad of accumulated error; at most 10.", in_range(0.0, 10.0))
    kd: float = setting(0.0, "Derivative gain, duty per rad/s^2; at most 1, as kp.", in_range(0.0, 1.0))
    wheel_max_speed_rad_s: float = setting(
        20.0,
        "Wheel speed at full duty; feed-forward duty = set-point / this. Between 1 and 200 rad/s: too small a value"
        " sends full duty for any command.",
        in_range(1.0, 200.0),
    )
    integral_limit: float = setting(
        0.5,
        "Largest duty magnitude the integral term may contribute (anti-windup bound); at most 1, full duty.",
        in_range(0.0, 1.0),
    )
    stall_timeout_s: float = setting(
        0.5,
        "A wheel driven more than stall_duty_margin beyond its feed-forward while it turns at less than a tenth of its"
        " set-point (a dead encoder, a blocked wheel) for this long has stalled: every motor stops until a fresh"
        " command.",
        in_range(0.05, 5.0),
    )
    stall_duty_margin: float = setting(
        0.15,
        "How far beyond the feed-forward duty the PID must push a wheel before it can count as stalled; below"
        " integral_limit, else the wound-up integral could never reach it.",
        in_range(0.01, 1.0),
    )

    def __post_init__(self) -> None:
        if self.ki > 0.0 and 0.0 < self.integral_limit <= self.stall_duty_margin:
            raise ValueError(
                f"stall_duty_margin ({self.stall_duty_margin}) must be below integral_limit ({self.integral_limit}):"
                " a wheel with a dead encoder would wind the integral up to integral_limit and never count as stalled"
            )


@dataclass(frozen=True, slots=True)
class RobotdConfig:
    """The whole configuration of robotd."""

    robot: RobotConfig = section(RobotConfig, "Robot geometry.")
    encoders: EncodersConfig = section(EncodersConfig, "Wheel encoders.")
    motors: MotorsConfig = section(MotorsConfig, "Motor drivers.")
    pigpiod: PigpiodConfig = section(PigpiodConfig, "Connection to pigpiod.")
    gpio: GpioConfig = section(GpioConfig, "GPIO back-end: pigpio, gpiod (Raspberry Pi 5) or auto.")
    marvelmind: MarvelmindConfig = section(MarvelmindConfig, "Marvelmind indoor positioning.")
    ekf: EkfConfig = section(EkfConfig, "Pose estimation.")
    teleop: TeleopConfig = section(TeleopConfig, "Remote control over UDP.")
    pose_socket: PoseSocketConfig = section(PoseSocketConfig, "Pose output.")
    control: ControlConfig = section(ControlConfig, "Motor control loop.")
    sim: SimConfig = section(SimConfig, "Virtual robot.")
    viewer: ViewerConfig = section(ViewerConfig, "Live view in Foxglove (robotd.viz).")
    fleet: FleetConfig = section(FleetConfig, "Fleet link to an MQTT broker (off by default).")


def _cross_checks(config: RobotdConfig) -> list[str]:
    """Problems that involve more than one field."""
    problems: list[str] = []
    owners: dict[int, str] = {}
    pins: list[tuple[str, int]] = []
    for wheel in WHEELS:
        enc: EncoderPins = getattr(config.encoders.wheels, wheel)
        mot: MotorPins = getattr(config.motors.wheels, wheel)
        pins += [(f"encoders.wheels.{wheel}.a", enc.a), (f"encoders.wheels.{wheel}.b", enc.b)]
        pins += [(f"motors.wheels.{wheel}.{name}", getattr(mot, name)) for name in ("enable", "in1", "in2")]
    for path, pin in pins:
        if pin in owners:
            problems.append(f"{path}: GPIO {pin} is already used by {owners[pin]}")
        else:
            owners[pin] = path
    if config.gpio.backend == "gpiod":  # `auto` is checked at start, on the board it resolves on (preflight)
        problems += gpiod_problems(config.motors)
    problems += _teleop_checks(config.teleop)
    if config.pose_socket.rate_hz > config.control.rate_hz * 10:
        problems.append(
            f"pose_socket.rate_hz: must be at most 10x control.rate_hz ({config.control.rate_hz}), "
            f"got {config.pose_socket.rate_hz}"
        )
    return problems


def _teleop_checks(teleop: TeleopConfig) -> list[str]:
    """Who may drive: a key, or no key on loopback only, never both."""
    if not teleop.allow_unauthenticated:
        return [] if teleop.key_file else ["teleop.key_file: required unless teleop.allow_unauthenticated is true"]
    if teleop.key_file:
        both = f"true together with teleop.key_file ({teleop.key_file}) would let unsigned datagrams drive"
        fix = "remove allow_unauthenticated, or set key_file: '' to run without a key on loopback"
        return [f"teleop.allow_unauthenticated: {both}: {fix}"]
    if not ipaddress.ip_address(teleop.bind).is_loopback:
        keyless = "teleop without a key (teleop.allow_unauthenticated) must listen on loopback (127.0.0.1 or ::1)"
        return [f"teleop.bind: {keyless}, got {teleop.bind}: anyone on that network could drive"]
    return []


def read_config_text(path: str | Path) -> str:
    """The text of a configuration file (a regular file of at most MAX_CONFIG_BYTES), or ConfigError."""
    try:
        return read_small_file(path, MAX_CONFIG_BYTES).decode("utf-8")
    except MissingFileError:
        raise ConfigError([f"{path}: no such configuration file"]) from None
    except SmallFileError as error:
        raise ConfigError([f"{path}: cannot read: {error}"]) from None
    except UnicodeDecodeError as error:
        raise ConfigError([f"{path}: cannot read: not UTF-8 text ({error.reason} at byte {error.start})"]) from None


def parse(text: str, source: str = "<config>") -> RobotdConfig:
    """Parse YAML text into a validated configuration, or raise ConfigError."""
    raw = parse_yaml(text, source)
    if raw is None:
        raw = {}
    if not isinstance(raw, dict):
        raise ConfigError([f"{source}: the top level must be a mapping of sections, got {type(raw).__name__}"])
    config = build(RobotdConfig, raw)
    problems = _cross_checks(config)
    if problems:
        raise ConfigError(problems)
    return config


def load(path: str | Path) -> RobotdConfig:
    """Read and validate a configuration file, or raise ConfigError."""
    return parse(read_config_text(path), str(path))


def config_reference() -> str:
    """The Markdown reference of every configuration key, generated from the schema."""
    return reference(RobotdConfig)


__all__ = ["WHEELS", "ConfigError", "RobotdConfig", "config_reference", "gated_preset", "load", "paper_preset", "parse"]
