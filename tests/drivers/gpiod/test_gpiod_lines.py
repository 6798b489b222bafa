"""The requests robotd makes through the real `gpiod` 2.x package (its request_lines replaced: no GPIO chip here)."""

from __future__ import annotations

import errno
import importlib.util
from datetime import timedelta
from pathlib import Path
from typing import Any

import gpiod
import pytest
from gpiod.line import Bias, Clock, Direction, Edge, Value

from drivers.gpiod import lines
from drivers.gpiod.lines import EventLineSettings, GpioUnavailableError, find_gpio_chip

OFFSETS = [5, 6, 13, 16, 19, 20, 21, 26]


class FakeRequest:
    """What gpiod.request_lines returns, reduced to what robotd uses."""

    def __init__(self) -> None:
        self.fd = 42
        self.values: dict[int, Value] = {5: Value.ACTIVE, 6: Value.INACTIVE, 13: Value.ACTIVE}
        self.written: list[dict[int | str, Value]] = []
        self.released = False

    def get_values(self, offsets: list[int]) -> list[Value]:
        return [self.values.get(offset, Value.INACTIVE) for offset in offsets]

    def set_values(self, values: dict[int | str, Value]) -> None:
        self.written.append(values)

    def release(self) -> None:
        self.released = True


@pytest.fixture
def requests(monkeypatch: pytest.MonkeyPatch) -> list[dict[str, Any]]:
    made: list[dict[str, Any]] = []

    def request_lines(path: str, config: dict[Any, gpiod.LineSettings], **options: Any) -> FakeRequest:
        request = FakeRequest()
        made.append({"path": path, "config": config, "request": request, **options})
        return request

    monkeypatch.setattr(gpiod, "request_lines", request_lines)
    return made


def test_encoder_lines_are_one_request_with_both_edges_and_a_large_buffer(requests: list[dict[str, Any]]) -> None:
    settings = EventLineSettings(chip="/dev/gpiochip0", pull="up", debounce_us=3, event_buffer_size=1024)
    opened = lines.open_event_lines(OFFSETS, settings)
    [made] = requests
    assert made["path"] == "/dev/gpiochip0"
    assert made["event_buffer_size"] == 1024
    assert made["consumer"] == "robotd-encoders"
    [(offsets, line_settings)] = made["config"].items()
    assert offsets == tuple(OFFSETS)
    assert (line_settings.direction, line_settings.edge_detection, line_settings.bias) == (
        Direction.INPUT,
        Edge.BOTH,
        Bias.PULL_UP,
    )
    assert (line_settings.debounce_period, line_settings.event_clock) == (timedelta(microseconds=3), Clock.MONOTONIC)
    assert opened.fd == 42
    assert opened.levels() == (1 << 5) | (1 << 13)
    opened.release()
    assert made["request"].released


def test_direction_lines_are_outputs_driven_low_and_written_at_once(requests: list[dict[str, Any]]) -> None:
    outputs = lines.open_output_lines([16, 20], "/dev/gpiochip0")
    [made] = requests
    [(offsets, line_settings)] = made["config"].items()
    assert offsets == (16, 20)
    assert (line_settings.direction, line_settings.output_value) == (Direction.OUTPUT, Value.INACTIVE)
    outputs.set_values({16: 1, 20: 0})
    assert made["request"].written == [{16: Value.ACTIVE, 20: Value.INACTIVE}]


@pytest.mark.parametrize(
    ("code", "hint"),
    [
        (errno.EBUSY, "another process holds them"),
        (errno.EACCES, "permission denied: add the service user to the gpio group"),
    ],
)
def test_a_refused_request_says_why(monkeypatch: pytest.MonkeyPatch, code: int, hint: str) -> None:
    def refuse(*_args: object, **_options: object) -> None:
        raise OSError(code, "refused")

    monkeypatch.setattr(gpiod, "request_lines", refuse)
    with pytest.raises(GpioUnavailableError, match=rf"encoder lines \[5, 6\] on /dev/gpiochip0: {hint}"):
        lines.open_event_lines([5, 6], EventLineSettings(chip="/dev/gpiochip0"))


def test_no_rp1_chip_is_a_clear_error(tmp_path: Path) -> None:
    (tmp_path / "gpiochip0").write_text("not a character device")
    with pytest.raises(GpioUnavailableError, match=r"no GPIO chip labelled 'pinctrl-rp1'.*Raspberry Pi 5"):
        find_gpio_chip(dev=str(tmp_path))


def test_without_the_gpiod_package_the_error_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    real_find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None if name == "gpiod" else real_find_spec(name))
    with pytest.raises(GpioUnavailableError, match=r"pip install 'robotd\[pi5\]'"):
        lines.open_output_lines([16], "/dev/gpiochip0")
