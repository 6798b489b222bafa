"""The Pi 5 stand-ins obey the real interfaces: kernel event records on a pipe, sysfs PWM rules, output requests."""

from __future__ import annotations

import errno
import math
import os
import struct
from pathlib import Path

import numpy as np
import pytest

from drivers.gpiod.lines import EventLineSettings
from drivers.gpiod.pwm import SysfsAttributes, find_pwm_chip
from drivers.virtual.event_pipe import VirtualEventLines
from drivers.virtual.output_lines import VirtualOutputLines
from drivers.virtual.pi5_wheels import VirtualPi5Wheels, WheelWiring
from drivers.virtual.pwm_sysfs import VirtualPwmSysfs

RECORD = struct.Struct("=QIIII24x")  # struct gpio_v2_line_event, as linux/gpio.h declares it


def read_records(fd: int) -> list[tuple[int, int, int, int, int]]:
    os.set_blocking(fd, False)
    data = b""
    while True:
        try:
            chunk = os.read(fd, 1 << 16)
        except BlockingIOError:
            break
        if not chunk:
            break
        data += chunk
    return [RECORD.unpack_from(data, offset) for offset in range(0, len(data), RECORD.size)]


def test_each_changed_requested_line_becomes_one_record_numbered_from_one() -> None:
    chip = VirtualEventLines(initial_levels=1 << 6)
    request = chip.open([5, 6], EventLineSettings())
    assert request.levels() == 1 << 6
    # 5 rises, then 5 falls and 6 falls together, then line 7 (not requested) changes alone.
    chip.drive_levels([1000, 2000, 3000], [(1 << 5) | (1 << 6), 0, 1 << 7], (1 << 5) | (1 << 6) | (1 << 7))
    assert read_records(request.fd) == [
        (1000, 1, 5, 1, 1),
        (2000, 2, 5, 2, 2),
        (2000, 2, 6, 3, 1),
    ]
    assert chip.levels == 1 << 7
    request.release()


def test_lost_events_leave_a_seqno_gap() -> None:
    chip = VirtualEventLines()
    request = chip.open([5], EventLineSettings())
    chip.lose_events(2)
    chip.drive_edges(5, [10, 20, 30, 40], [1, 0, 1, 0])
    assert [(seqno, line_seqno) for _, _, _, seqno, line_seqno in read_records(request.fd)] == [(3, 3), (4, 4)]
    assert chip.events_dropped == 2
    request.release()


def test_a_full_pipe_drops_what_does_not_fit_and_the_gap_shows() -> None:
    chip = VirtualEventLines()
    request = chip.open([5], EventLineSettings())
    edges = 4000  # about three times what the pipe holds
    chip.drive_edges(5, np.arange(edges), np.arange(1, edges + 1) % 2)
    records = read_records(request.fd)
    assert 0 < len(records) < edges
    assert chip.events_written == len(records)
    assert chip.events_written + chip.events_dropped == edges
    chip.drive_edges(5, [edges + 1], [edges % 2 == 0])
    [(_, _, _, seqno, _)] = read_records(request.fd)
    assert seqno == edges + 1  # the next event still carries its own number: the loss is visible
    request.release()


def test_a_second_request_for_held_lines_is_refused_and_unplug_ends_the_stream() -> None:
    chip = VirtualEventLines()
    request = chip.open([5, 6], EventLineSettings())
    with pytest.raises(OSError, match="busy"):
        chip.open([6], EventLineSettings())
    chip.unplug()
    assert os.read(request.fd, 48) == b""  # end of file
    request.release()
    chip.open([6], EventLineSettings()).release()


def test_pwm_sysfs_layout_and_the_kernels_rules(tmp_path: Path) -> None:
    sysfs = VirtualPwmSysfs(tmp_path)
    chip = find_pwm_chip(root=sysfs.class_root)
    assert chip.name == "pwmchip2"  # the RP1's PWM0 by its device path, though pwmchip0 exists
    assert os.path.realpath(chip).endswith("1f00098000.pwm/pwm/pwmchip2")
    sysfs.write(chip / "export", "1")
    channel = chip / "pwm1"
    assert {p.name for p in channel.iterdir()} >= {"period", "duty_cycle", "enable", "polarity"}

    def refused(path: Path, value: str) -> int:
        with pytest.raises(OSError, match=r"\[Errno") as error:
            sysfs.write(path, value)
        return error.value.errno or 0

    assert refused(chip / "export", "1") == errno.EBUSY
    assert refused(chip / "export", "4") == errno.ENODEV
    assert refused(channel / "enable", "1") == errno.EINVAL  # period 0
    sysfs.write(channel / "period", "1000")
    assert refused(channel / "duty_cycle", "1001") == errno.EINVAL
    sysfs.write(channel / "duty_cycle", "250")
    sysfs.write(channel / "enable", "1")
    assert refused(channel / "polarity", "inversed") == errno.EBUSY
    assert refused(channel / "period", "200") == errno.EINVAL  # below the duty
    assert sysfs.output(1) == 0.25
    assert sysfs.journal == [
        {"export": "1"},
        {"pwm1/period": "1000"},
        {"pwm1/duty_cycle": "250"},
        {"pwm1/enable": "1"},
    ]
    SysfsAttributes().write(channel / "enable", "0")  # another process's plain write: the file changes
    assert sysfs.output(1) == 0.0
    sysfs.write(chip / "unexport", "1")
    assert sysfs.exported() == []


def test_output_lines_record_each_call_as_one_write_and_refuse_held_lines() -> None:
    chip = VirtualOutputLines()
    request = chip.open([16, 20])
    request.set_values({16: 1, 20: 0})
    with pytest.raises(OSError, match="held by another request"):
        chip.open([20, 21])
    request.release()
    assert chip.journal == [{"gpio16": "0", "gpio20": "0"}, {"gpio16": "1", "gpio20": "0"}]
    assert chip.held == set()


def test_the_wheels_behind_the_stand_ins_turn_pwm_and_direction_into_quadrature_edges(tmp_path: Path) -> None:
    sysfs, lines, edges = VirtualPwmSysfs(tmp_path), VirtualOutputLines(), VirtualEventLines()
    wheel = WheelWiring(enable=12, in1=16, in2=20, a=4, b=17)
    wheels = VirtualPi5Wheels(
        [wheel], sysfs=sysfs, outputs=lines, edges=edges, counts_per_rev=6800, max_speed_rad_s=20.0
    )
    request = edges.open([4, 17], EventLineSettings())
    for name, value in (("export", "0"), ("pwm0/period", "1000000"), ("pwm0/duty_cycle", "250000")):
        sysfs.write(sysfs.chip / name, value)
    sysfs.write(sysfs.chip / "pwm0" / "enable", "1")
    outputs = lines.open([16, 20])
    outputs.set_values({16: 0, 20: 1})  # backward at duty 0.25: 5 rad/s
    wheels.step(1_000_000_000)
    wheels.step(1_200_000_000)  # 0.2 s: one rad, 6800 / 2 pi counts backward
    records = read_records(request.fd)
    position = math.floor(-6800 / (2 * math.pi))  # the count at -1 rad: floor, as the virtual robot counts
    assert len(records) == -position
    assert {offset for _, _, offset, _, _ in records} == {4, 17}
    assert all(1_000_000_000 < stamp <= 1_200_000_000 for stamp, *_ in records)
    assert wheels.angles == [pytest.approx(-1.0)]
    a_level, b_level = (edges.levels >> 4) & 1, (edges.levels >> 17) & 1
    assert ((a_level << 1) | b_level) == [0, 2, 3, 1][position % 4]
