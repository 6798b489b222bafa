"""Helpers for the gpiod back-end tests: edge-event records written out by hand, one struct.pack per edge; motors on
the sysfs PWM and output-line stand-ins."""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence

from drivers.gpiod.motors import GpiodMotors
from drivers.gpiod.pwm import find_pwm_chip
from drivers.settings import MotorPinsLike
from drivers.virtual.event_pipe import VirtualEventLines
from drivers.virtual.output_lines import VirtualOutputLines
from drivers.virtual.pwm_sysfs import VirtualPwmSysfs
from drivers.virtual.quadrature_signal import encoder_words, merge_streams
from drivers.wheels.quadrature import EncoderWiring
from robotd.sim.edges import wheel_edges

RECORD = struct.Struct("=QIIII24x")
"""struct gpio_v2_line_event as linux/gpio.h declares it: u64 timestamp_ns, u32 id, offset, seqno, line_seqno,
u32 padding[6]."""
RISING, FALLING = 1, 2
GRAY = [0, 2, 3, 1]  # state (A << 1) | B at x4 positions 0, 1, 2, 3: forward, A leads B


def stand_in_motors(
    wheels: Sequence[MotorPinsLike],
    sysfs: VirtualPwmSysfs,
    lines: VirtualOutputLines,
    *,
    frequency_hz: float = 1000.0,
    duty_limit: float = 1.0,
    watchdog: bool = False,
    heartbeat_timeout_s: float | None = None,
) -> GpiodMotors:
    """GpiodMotors whose PWM is the sysfs stand-in and whose direction lines are the output-line stand-in."""
    return GpiodMotors(
        wheels,
        frequency_hz=frequency_hz,
        duty_limit=duty_limit,
        pwm_chip=find_pwm_chip(root=sysfs.class_root),
        attributes=sysfs,
        open_outputs=lines.open,
        watchdog=watchdog,
        heartbeat_timeout_s=heartbeat_timeout_s,
    )


def pack(timestamp_ns: int, rising: bool, offset: int, seqno: int, line_seqno: int) -> bytes:
    return RECORD.pack(timestamp_ns, RISING if rising else FALLING, offset, seqno, line_seqno)


def walk_records(
    wiring: list[EncoderWiring], moves: list[list[int]], start: int = 0, t0_ns: int = 1_000_000, spacing_ns: int = 7_000
) -> tuple[bytes, list[int]]:
    """Records of each wheel stepping through its +1/-1 moves from x4 position `start`, wheels taking turns, seqnos
    from 1; and each wheel's net x4 count (before its sign)."""
    records, seqno, t = [], 0, t0_ns
    line_seqno: dict[int, int] = {}
    positions = [start] * len(wiring)
    longest = max(len(m) for m in moves)
    for step in range(longest):
        for wheel, encoder in enumerate(wiring):
            if step >= len(moves[wheel]):
                continue
            before = GRAY[positions[wheel] % 4]
            positions[wheel] += moves[wheel][step]
            after = GRAY[positions[wheel] % 4]
            line, level = (encoder.a, after >> 1) if (before ^ after) == 2 else (encoder.b, after & 1)
            seqno += 1
            line_seqno[line] = line_seqno.get(line, 0) + 1
            t += spacing_ns
            records.append(pack(t, bool(level), line, seqno, line_seqno[line]))
    return b"".join(records), [p - start for p in positions]


def initial_word(wiring: list[EncoderWiring], position: int) -> int:
    """The level word of every encoder at x4 `position`."""
    state = GRAY[position % 4]
    return sum(((state >> 1) << e.a) | ((state & 1) << e.b) for e in wiring)


def drive_turns(
    chip: VirtualEventLines,
    wiring: list[EncoderWiring],
    turns: list[float],
    t0_ns: int,
    duration_ns: int,
    counts_per_rev: int,
    start_turns: list[float] | None = None,
) -> list[int]:
    """Turn each wheel from `start_turns[i]` (default 0) to `turns[i]` revolutions over `duration_ns`, the edges made
    as the virtual robot makes them (robotd.sim.edges, drivers.virtual.quadrature_signal); returns the x4 positions."""
    streams, mask, ends = [], 0, []
    starts = start_turns or [0.0] * len(wiring)
    for encoder, start, turn in zip(wiring, starts, turns, strict=True):
        angle0, angle1 = start * 2 * math.pi, turn * 2 * math.pi
        ticks, counts = wheel_edges(angle0, angle1, 0, duration_ns // 1000, counts_per_rev)
        bits = (1 << encoder.a) | (1 << encoder.b)
        streams.append((t0_ns + ticks * 1000, encoder_words(counts, encoder.a, encoder.b), bits))
        mask |= bits
        ends.append(math.floor(angle1 * (counts_per_rev / (2.0 * math.pi))))  # as wheel_edges counts
    stamps, words = merge_streams(streams, chip.levels)
    chip.drive_levels(stamps, words, mask)
    return ends
