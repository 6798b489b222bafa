"""`robotd simulate`: a scenario run through the virtual robot in simulated time, as a sensor log with truth.

Theory of operation: a discrete-event loop on an integer microsecond clock (so that coincident events of different
rates coincide exactly and runs repeat byte for byte). The timelines are the physics and truth samples, the encoder
publications, the daemon's control periods, the remote control's commands, and the hedgehog's measurements and
packet arrivals. Between two events the physics advances with the duties held (the motors are solved in closed
form). The control law is the daemon's own `MotionController`, stepped at the control rate with the last command
and the wheel speeds measured from the published encoder counts, as the daemon does; its duties are quantised as
gpiozero quantises them on pigpio (a PWM range of 10000, truncated).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import TextIO

from drivers.virtual.marvelmind import HedgehogPacket
from robotd.config.model import RobotdConfig
from robotd.daemon.control import MotionController
from robotd.kinematics import Twist
from robotd.logs.sensorlog import Command, Event, IpsFix, IpsLost, LogWriter, Meta, Truth, Wheels
from robotd.sim import variants
from robotd.sim.scenarios import Scenario
from robotd.sim.scenarios import build as build_scenario
from robotd.sim.world import build_world, geometry_of, scenario_params

US = 1_000_000
PWM_RANGE = 10_000  # gpiozero's PiGPIOFactory sets this range on every PWM pin


def quantised_duty(duty: float) -> float:
    """A duty as it reaches the motor through gpiozero and pigpio: truncated to 1/PWM_RANGE."""
    return math.trunc(duty * PWM_RANGE) / PWM_RANGE


def fix_event(packet: HedgehogPacket, arrival_s: float) -> IpsFix | IpsLost:
    """The log event a host records for a position packet arriving at arrival_s."""
    if not packet.available:
        return IpsLost(arrival_s)
    return IpsFix(
        t=arrival_s,
        x=packet.x_mm / 1000.0,
        y=packet.y_mm / 1000.0,
        z=packet.z_mm / 1000.0,
        t_meas=arrival_s - packet.time_shift_ms / 1000.0,
    )


def meta_for(config: RobotdConfig, source: str) -> Meta:
    """The log header describing the simulated robot."""
    r = config.robot
    robot = {
        "wheel_radius": r.wheel_radius_m,
        "lx": r.lx_m,
        "ly": r.ly_m,
        "counts_per_rev": config.encoders.counts_per_rev,
        "ips_offset": list(r.ips_offset_m),
    }
    return Meta(robot=robot, source=source)


@dataclass(slots=True)
class _Timeline:
    """A periodic event on the microsecond clock."""

    period_us: int
    next_us: int = 0

    def fire(self, now_us: int) -> bool:
        """Whether the event is due at now_us; if so, schedule the next one."""
        if self.next_us != now_us:
            return False
        self.next_us += self.period_us
        return True


@dataclass(slots=True)
class _SpeedMeter:
    """Wheel speeds from the difference of published counts between two control periods."""

    radians_per_count: float
    counts: tuple[int, int, int, int] = (0, 0, 0, 0)
    at_us: int = 0
    speeds: tuple[float, float, float, float] = field(default=(0.0, 0.0, 0.0, 0.0))

    def update(self, counts: tuple[int, int, int, int], at_us: int) -> tuple[float, float, float, float]:
        """The speeds (rad/s) since the previous update; the previous speeds if no new counts were published."""
        if at_us > self.at_us:
            scale = self.radians_per_count * US / (at_us - self.at_us)
            s = [(new - old) * scale for new, old in zip(counts, self.counts, strict=True)]
            self.speeds = (s[0], s[1], s[2], s[3])
            self.counts, self.at_us = counts, at_us
        return self.speeds


def run(config: RobotdConfig, scenario: Scenario, seed: int) -> Iterator[Event]:
    """The events of one simulated run, in arrival order (truth included), ending shortly after the scenario."""
    world = build_world(config, seed, scenario)
    robot, hedgehog = world.robot, world.hedgehog
    cpr = config.encoders.counts_per_rev
    controller = MotionController(geometry_of(config), config.control, config.teleop, config.motors.duty_limit)
    truth = _Timeline(round(US / config.sim.physics_rate_hz))
    wheels = _Timeline(round(US / config.encoders.publish_rate_hz))
    control = _Timeline(round(US / config.control.rate_hz))
    teleop = _Timeline(round(US / config.sim.teleop_rate_hz))
    end_us = round((scenario.duration_s + 1.0) * US)  # a second at rest after the last command
    meter = _SpeedMeter(2.0 * math.pi / cpr)
    published = (0, 0, 0, 0)
    published_us = 0
    command: Twist | None = None
    command_us = 0
    duties = (0.0, 0.0, 0.0, 0.0)
    now_us = 0
    while now_us <= end_us:
        now = now_us / US
        if round(hedgehog.next_measurement_s * US) <= now_us:
            hedgehog.measure(now, *world.beacon_xy())
        for packet in hedgehog.due(now):
            yield fix_event(packet, now)
        if teleop.fire(now_us) and now < scenario.duration_s:
            vx, vy, wz = scenario.command_at(now)
            command, command_us = Twist(vx, vy, wz), now_us
            yield Command(now, vx, vy, wz)
        if wheels.fire(now_us):
            published, published_us = robot.encoder_counts(cpr), now_us
            yield Wheels(now, published)
        if control.fire(now_us):
            speeds = meter.update(published, published_us)
            raw = controller.step(now, command, None if command is None else command_us / US, speeds)
            duties = (quantised_duty(raw[0]), quantised_duty(raw[1]), quantised_duty(raw[2]), quantised_duty(raw[3]))
        if truth.fire(now_us):
            pose = robot.body
            yield Truth(now, pose.x, pose.y, pose.theta)
        # every candidate lies after now_us, so the clock always advances (end_us + 1 ends the loop)
        arrival_us = math.ceil(hedgehog.next_arrival_s * US) if hedgehog.next_arrival_s < math.inf else end_us + 1
        next_us = min(
            truth.next_us,
            wheels.next_us,
            control.next_us,
            teleop.next_us,
            max(now_us + 1, round(hedgehog.next_measurement_s * US)),
            max(now_us + 1, arrival_us),
            end_us + 1,
        )
        robot.step(duties, (next_us - now_us) / US)
        now_us = next_us


@dataclass(frozen=True, slots=True)
class RunSummary:
    """What one offline run produced."""

    scenario: str
    seed: int
    loops: int
    simulated_s: float
    events: dict[str, int]


def simulate(config: RobotdConfig, scenario_name: str, seed: int, loops: int, out: TextIO) -> RunSummary:
    """Write the sensor log of one scenario run to `out`; the same arguments give the same bytes."""
    source = f"robotd simulate {scenario_name} --seed {seed} --loops {loops}"
    if scenario_name in variants.VARIANTS:
        variant = variants.build(scenario_name, config, scenario_params(config.sim), loops, seed)
        writer = LogWriter(out, meta_for(variant.described, source))
        events = variants.logged(variant, run(variant.world, variant.scenario, seed))
    else:
        scenario = build_scenario(scenario_name, scenario_params(config.sim), loops, seed)
        writer = LogWriter(out, meta_for(config, source))
        events = run(config, scenario, seed)
    counts: dict[str, int] = {}
    last_t = 0.0
    for event in events:
        writer.write(event)
        kind = type(event).__name__
        counts[kind] = counts.get(kind, 0) + 1
        last_t = event.t
    writer.flush()
    return RunSummary(scenario_name, seed, loops, last_t, counts)
