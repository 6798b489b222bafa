"""Scenarios: what a remote-control operator sends, as timed open-loop teleop commands.

A scenario is a list of segments, each a constant body twist held for a duration, the way an operator holds a stick:
nobody closes the loop on position, so the true path drifts with the floor. A scenario may also force the beacon to
be lost over some intervals (the `outage` scenario). Each scenario starts and ends at rest.
"""

from __future__ import annotations

import bisect
import itertools
import math
import random
from dataclasses import dataclass, field

SCENARIOS = ("square", "figure8", "random", "outage")


@dataclass(frozen=True, slots=True)
class Segment:
    """A constant command (m/s, m/s, rad/s) held for duration_s."""

    duration_s: float
    vx: float = 0.0
    vy: float = 0.0
    wz: float = 0.0


@dataclass(frozen=True, slots=True)
class ScenarioParams:
    """How the operator drives."""

    speed_mps: float = 0.3
    side_m: float = 3.0
    pause_s: float = 1.0
    outage_s: float = 20.0


@dataclass(frozen=True, slots=True)
class Scenario:
    """A named sequence of segments, and the intervals (start, end) in which the beacon is forced lost."""

    name: str
    segments: tuple[Segment, ...]
    outages: tuple[tuple[float, float], ...] = ()
    starts: tuple[float, ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        starts = tuple(itertools.accumulate((s.duration_s for s in self.segments[:-1]), initial=0.0))
        object.__setattr__(self, "starts", starts)  # frozen: computed once, read at every command

    @property
    def duration_s(self) -> float:
        """The length of the whole scenario."""
        return math.fsum(s.duration_s for s in self.segments)

    def command_at(self, t: float) -> tuple[float, float, float]:
        """The command held at time t (rest before the start and after the end)."""
        if t < 0.0 or t >= self.duration_s:
            return (0.0, 0.0, 0.0)
        segment = self.segments[bisect.bisect_right(self.starts, t) - 1]
        return (segment.vx, segment.vy, segment.wz)


def square(params: ScenarioParams, loops: int) -> Scenario:
    """The paper's square: +x, slide to -y, -x, slide to +y, each one side long, with a stop after each leg."""
    leg = params.side_m / params.speed_mps
    v = params.speed_mps
    pause = Segment(params.pause_s)
    legs = (Segment(leg, vx=v), Segment(leg, vy=-v), Segment(leg, vx=-v), Segment(leg, vy=v))
    one_loop = tuple(s for leg_segment in legs for s in (leg_segment, pause))
    return Scenario("square", (Segment(2.0 * params.pause_s), *(one_loop * loops)))


def figure8(params: ScenarioParams, loops: int) -> Scenario:
    """A figure of eight: a counter-clockwise circle then a clockwise one, of diameter two thirds of the side."""
    radius = params.side_m / 3.0
    circle = 2.0 * math.pi * radius / params.speed_mps
    turn = params.speed_mps / radius
    one_loop = (Segment(circle, vx=params.speed_mps, wz=turn), Segment(circle, vx=params.speed_mps, wz=-turn))
    pause = Segment(2.0 * params.pause_s)
    return Scenario("figure8", (pause, *(one_loop * loops), pause))


def random_teleop(params: ScenarioParams, loops: int, seed: int) -> Scenario:
    """Random stick movements: 1-3 s commands in every direction with stops, about 40 s per loop."""
    return random_commands(params, loops, random.Random(f"robotd-sim:{seed}:teleop"), "random", lateral=True)


def random_commands(
    params: ScenarioParams, loops: int, rng: random.Random, name: str, *, lateral: bool, max_turn: float = 0.6
) -> Scenario:
    """1-3 s commands (a fifth of them stops) drawn from `rng`, about 40 s per loop; sideways ones only if `lateral`
    (a differential-drive base has none)."""
    v = params.speed_mps
    segments = [Segment(2.0 * params.pause_s)]
    total = 0.0
    while total < 40.0 * loops:
        duration = rng.uniform(1.0, 3.0)
        if rng.random() < 0.2:
            segments.append(Segment(duration))
        else:
            vx = rng.uniform(-v, v)
            vy = rng.uniform(-v, v) if lateral else 0.0
            segments.append(Segment(duration, vx, vy, rng.uniform(-max_turn, max_turn)))
        total += duration
    segments.append(Segment(2.0 * params.pause_s))
    return Scenario(name, tuple(segments))


def outage(params: ScenarioParams, loops: int) -> Scenario:
    """The square with the beacon lost for `outage_s` in the middle of the run."""
    base = square(params, loops)
    start = max(0.0, base.duration_s / 2.0 - params.outage_s / 2.0)
    return Scenario("outage", base.segments, ((start, start + params.outage_s),))


def build(name: str, params: ScenarioParams, loops: int = 3, seed: int = 1) -> Scenario:
    """The scenario called `name` (one of SCENARIOS), repeated `loops` times."""
    if loops < 1:
        raise ValueError(f"loops must be at least 1, got {loops}")
    match name:
        case "square":
            return square(params, loops)
        case "figure8":
            return figure8(params, loops)
        case "random":
            return random_teleop(params, loops, seed)
        case "outage":
            return outage(params, loops)
    raise ValueError(f"unknown scenario {name!r}; known: {', '.join(SCENARIOS)}")
