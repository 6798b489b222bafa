"""`robotd replay` on logs no sensor wrote: a bad line is skipped with its line number, a log that cannot be replayed
is refused in one line with a sysexits status, an output path in the way is one line too; never a traceback."""

from __future__ import annotations

import functools
import io
import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
from paths import REPO

from robotd import cli
from robotd.config.model import load
from robotd.sim.offline import simulate

EX_DATAERR, EX_NOINPUT, EX_CANTCREAT = 65, 66, 73
INSERT_AT = 60  # a wheel sample's place in the log, after the start


@functools.cache
def _drive() -> tuple[str, ...]:
    text = io.StringIO()
    simulate(load(REPO / "config" / "sim.yaml"), "square", 5, 1, text)
    return tuple(text.getvalue().splitlines(keepends=True))


def good_lines() -> list[str]:
    """One loop of the virtual robot's square with truth, as JSON lines (the meta line first)."""
    return list(_drive())


def replay(tmp_path: Path, lines: list[str], capsys: pytest.CaptureFixture[str], name: str) -> tuple[int, str, Path]:
    """`robotd replay LOG --out DIR` on these lines: the status, stderr and the output folder."""
    log = tmp_path / f"{name}.jsonl"
    log.write_text("".join(lines), encoding="utf-8")
    out = tmp_path / f"{name}-out"
    status = cli.main(["replay", str(log), "--out", str(out)])
    return status, capsys.readouterr().err, out


def inserted(lines: list[str], make: Callable[[float], str]) -> list[str]:
    """The lines with one more, made from the time of the line before it (so that only its content is bad)."""
    t = json.loads(lines[INSERT_AT - 1])["t"]
    return [*lines[:INSERT_AT], make(t) + "\n", *lines[INSERT_AT:]]


BAD_LINES = {
    "infinite time": lambda t: '{"t": Infinity, "type": "wheels", "ticks": [0, 0, 0, 0]}',
    "huge time": lambda t: '{"t": 1e300, "type": "ips", "x": 0.1, "y": 0.2}',
    "negative huge time": lambda t: '{"t": -1e300, "type": "truth", "x": 0.1, "y": 0.2}',
    "nan fix": lambda t: f'{{"t": {t}, "type": "ips", "x": NaN, "y": 0.2}}',
    "infinite t_meas": lambda t: f'{{"t": {t}, "type": "ips", "x": 0.1, "y": 0.2, "t_meas": -Infinity}}',
    "infinite twist": lambda t: f'{{"t": {t}, "type": "twist", "vx": Infinity, "vy": 0, "wz": 0}}',
    "deep nesting": lambda t: "[" * 100_000 + "]" * 100_000,
    "deep nesting in a field": lambda t: f'{{"t": {t}, "type": "ips", "x": {"[" * 50_000}{"]" * 50_000}, "y": 0}}',
    "integer time of 400 digits": lambda t: '{"t": 1' + "0" * 400 + ', "type": "cmd", "vx": 0, "vy": 0, "wz": 0}',
    "integer of 5000 digits": lambda t: f'{{"t": {t}, "type": "wheels", "ticks": [1{"0" * 5000}, 0, 0, 0]}}',
    "1e999": lambda t: f'{{"t": {t}, "type": "truth", "x": 1e999, "y": 0}}',
    "fix beyond any map": lambda t: f'{{"t": {t}, "type": "ips", "x": 0.1, "y": 1e300}}',
    "truth heading wound 1e18 times": lambda t: f'{{"t": {t}, "type": "truth", "x": 0.1, "y": 0.2, "theta": 9e18}}',
    "tick jump of 9e18": lambda t: f'{{"t": {t}, "type": "wheels", "ticks": [9000000000000000000, 0, 0, 0]}}',
    "tick jump of -9e18": lambda t: f'{{"t": {t}, "type": "wheels", "ticks": [0, 0, 0, -9223372036854775808]}}',
}
EXPECTED = {
    "infinite time": "a number that is not finite (Infinity or NaN)",
    "huge time": "'t' = 1e+300 is not within ±9.0072e+09 s",
    "negative huge time": "'t' = -1e+300 is not within ±9.0072e+09 s",
    "nan fix": "a number that is not finite (Infinity or NaN)",
    "infinite t_meas": "a number that is not finite (Infinity or NaN)",
    "infinite twist": "a number that is not finite (Infinity or NaN)",
    "deep nesting": "Expected `object`, got `array`",
    "deep nesting in a field": "Expected `float`, got `array` - at `$.x`",
    "integer time of 400 digits": "Number out of range - at `$.t` (a number beyond any double",
    "integer of 5000 digits": "Integer value out of range - at `$.ticks[0]` (a number beyond any double",
    "1e999": "Number out of range - at `$.x` (a number beyond any double",
    "fix beyond any map": "'y' = 1e+300 is not within ±1e+07 m",
    "truth heading wound 1e18 times": "'theta' = 9e+18 is not within ±1e+06 rad",
    "tick jump of 9e18": "front-left counts jump by 9e+18",
    "tick jump of -9e18": "rear-right counts jump by -9.22e+18",
}


@pytest.mark.parametrize("case", BAD_LINES)
def test_a_bad_line_is_skipped_with_its_line_number_and_the_rest_replays_as_without_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], case: str
) -> None:
    lines = good_lines()
    status, err, out = replay(tmp_path, lines, capsys, "good")
    assert (status, err) == (0, "")
    status, err, damaged = replay(tmp_path, inserted(lines, BAD_LINES[case]), capsys, "bad")
    assert status == 0
    assert len(err.splitlines()) == 1, err
    assert f": line {INSERT_AT + 1}: " in err
    assert EXPECTED[case] in err
    assert err.rstrip().endswith("(skipped)")
    assert (damaged / "estimates.jsonl").read_bytes() == (out / "estimates.jsonl").read_bytes()
    assert (damaged / "metrics.json").read_text() == (out / "metrics.json").read_text()


def test_a_counter_that_stays_jumped_is_listed_up_to_twenty_lines_then_counted(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    lines = good_lines()
    jumped = []
    for index, line in enumerate(lines):
        event = json.loads(line)
        if index >= INSERT_AT and event["type"] == "wheels":
            event["ticks"][1] += 2**62
        jumped.append(json.dumps(event) + "\n")
    status, err, out = replay(tmp_path, jumped, capsys, "jumped")
    assert status == 0  # the drive up to the jump, and the fixes, are still replayed
    shown = err.splitlines()
    assert len(shown) == 21
    assert all("front-right counts jump by 4.61e+18" in line for line in shown[:20])
    wheel_lines = sum(1 for line in lines[INSERT_AT:] if '"wheels"' in line)
    assert shown[20].endswith(f"... and {wheel_lines - 20} more bad lines (skipped)")
    assert json.loads((out / "metrics.json").read_text())["ips"]["samples"] > 10  # the fixes after it are scored


def test_a_glitch_in_the_first_wheel_sample_is_that_sample_not_all_the_others(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    lines = good_lines()
    first = next(i for i, line in enumerate(lines) if '"wheels"' in line)
    event = json.loads(lines[first])
    event["ticks"] = [0, 0, 7 * 10**17, 0]
    status, err, _ = replay(tmp_path, [*lines[:first], json.dumps(event) + "\n", *lines[first + 1 :]], capsys, "first")
    assert status == 0
    assert err.splitlines() == [err.splitlines()[0]]
    assert f"line {first + 1}: rear-left counts jump by 7e+17" in err


def _counter(count: int, bits: int, *, signed: bool) -> int:
    """What a `bits`-bit encoder counter reads after `count` counts."""
    value = count % (1 << bits)
    return value - (1 << bits) if signed and value >= 1 << (bits - 1) else value


@pytest.mark.parametrize(("bits", "signed", "start"), [(16, False, 0), (16, True, 0), (32, True, 2**31 - 20_000)])
def test_a_wheel_counter_that_wraps_is_unwrapped_and_said_and_replays_as_cumulative_counts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], bits: int, signed: bool, start: int
) -> None:
    lines = good_lines()
    status, err, out = replay(tmp_path, lines, capsys, "good")
    assert (status, err) == (0, "")
    wrapped = []
    for line in lines:
        event = json.loads(line)
        if event.get("type") == "wheels":
            event["ticks"] = [_counter(start + count, bits, signed=signed) for count in event["ticks"]]
        wrapped.append(json.dumps(event) + "\n")
    assert wrapped != lines
    status, err, unwrapped = replay(tmp_path, wrapped, capsys, "wrapped")
    assert status == 0
    notes = err.splitlines()
    assert notes, "no wrap was found"
    assert all(f"counts: a {bits}-bit counter, unwrapped" in note for note in notes), err
    assert not any("skipped" in note for note in notes)  # nothing lost: a 16-bit wrap read as motion threw the
    # robot metres, a 32-bit one was a jump no wheel makes and lost every wheel sample after it
    assert (unwrapped / "estimates.jsonl").read_bytes() == (out / "estimates.jsonl").read_bytes()


def test_a_log_whose_times_go_back_is_refused_at_that_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    lines = good_lines()
    event = json.loads(lines[INSERT_AT])
    back = [*lines[:INSERT_AT], json.dumps({**event, "t": event["t"] - 0.5}) + "\n", *lines[INSERT_AT + 1 :]]
    status, err, out = replay(tmp_path, back, capsys, "back")
    assert status == EX_DATAERR
    assert len(err.splitlines()) == 1, err
    assert f"line {INSERT_AT + 1}: time goes backwards" in err
    assert f"on line {INSERT_AT}: a sensor log is in arrival order" in err
    assert not (out / "estimates.jsonl").exists()


def test_a_merged_log_is_refused_unless_sort_is_asked_for_and_then_replays_as_the_log_in_order(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    lines = good_lines()
    # two recordings merged one after the other: the fixes after the rest (each one arrives after a later line)
    fixes = [line for line in lines[1:] if '"ips"' in line]
    merged = [lines[0], *(line for line in lines[1:] if '"ips"' not in line), *fixes]
    status, err, _ = replay(tmp_path, merged, capsys, "merged")
    assert status == EX_DATAERR
    assert "--sort takes it in time order" in err
    _, _, in_order = replay(tmp_path, lines, capsys, "in-order")
    log = tmp_path / "merged.jsonl"
    out = tmp_path / "sorted-out"
    assert cli.main(["replay", str(log), "--sort", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert f"{len(fixes)} lines came after a later time: taken in time order (--sort)" in err, err
    assert (out / "estimates.jsonl").read_bytes() == (in_order / "estimates.jsonl").read_bytes()


def test_a_reversed_log_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    lines = good_lines()
    reversed_lines = [lines[0], *reversed(lines[1:])]
    times = [json.loads(line)["t"] for line in reversed_lines[1:]]
    first_back = next(i for i in range(1, len(times)) if times[i] < times[i - 1]) + 2  # file lines count from 1
    status, err, _ = replay(tmp_path, reversed_lines, capsys, "reversed")
    assert status == EX_DATAERR
    assert len(err.splitlines()) == 1, err
    assert f"line {first_back}: time goes backwards" in err


def test_a_log_in_negative_time_replays_as_the_same_log_from_zero(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    lines = good_lines()
    shifted = [lines[0]]
    for line in lines[1:]:
        event = json.loads(line)
        for key in ("t", "t_meas"):
            if key in event:
                event[key] = round(event[key] - 1000.0, 6)
        shifted.append(json.dumps(event) + "\n")
    assert replay(tmp_path, lines, capsys, "zero")[:2] == (0, "")
    status, err, out = replay(tmp_path, shifted, capsys, "negative")
    assert (status, err) == (0, "")
    zero = json.loads((tmp_path / "zero-out" / "metrics.json").read_text())
    negative = json.loads((out / "metrics.json").read_text())
    for method in ("odometry", "ips", "ekf"):
        assert negative[method]["rmse_m"] == pytest.approx(zero[method]["rmse_m"], abs=1e-3), method


@pytest.mark.parametrize(
    ("content", "said"),
    [
        ("", "no events"),
        (None, "no events"),  # the meta line alone
        ('{"t": Infinity, "type": "wheels", "ticks": [0, 0, 0, 0]}\n', "no events"),
    ],
)
def test_a_log_without_events_says_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], content: str | None, said: str
) -> None:
    lines = [good_lines()[0]] if content is None else [content]
    status, err, out = replay(tmp_path, lines, capsys, "empty")
    assert status == EX_DATAERR
    assert err.splitlines()[-1].endswith(f"{said}; nothing replayed")
    assert len(err.splitlines()) == (2 if "Infinity" in (content or "") else 1)  # the bad line, then the verdict
    assert not (out / "estimates.jsonl").exists()


def test_an_out_path_that_is_a_file_is_one_line_and_no_replay(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log = tmp_path / "drive.jsonl"
    log.write_text("".join(good_lines()), encoding="utf-8")
    in_the_way = tmp_path / "results"
    in_the_way.write_text("keep me")
    assert cli.main(["replay", str(log), "--out", str(in_the_way)]) == EX_CANTCREAT
    err = capsys.readouterr().err
    assert err == f"robotd replay: --out {in_the_way}: cannot make it a directory: a file is in the way\n"
    assert in_the_way.read_text() == "keep me"
    assert cli.main(["replay", str(log), "--out", str(in_the_way / "below")]) == EX_CANTCREAT
    assert len(capsys.readouterr().err.splitlines()) == 1


@pytest.mark.parametrize(
    ("key", "value"), [("wheel_radius", 1e300), ("counts_per_rev", 0.5), ("lx", -1.0), ("ips_offset", [1e300, 0])]
)
def test_meta_robot_values_no_robot_has_are_one_line_and_the_configuration_is_used(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], key: str, value: object
) -> None:
    lines = good_lines()
    status, _, out = replay(tmp_path, lines, capsys, "good")
    meta = json.loads(lines[0])
    meta["robot"][key] = value
    status, err, damaged = replay(tmp_path, [json.dumps(meta) + "\n", *lines[1:]], capsys, "meta")
    assert status == 0
    assert len(err.splitlines()) == 1, err
    assert f"meta.robot.{key}: must be " in err
    assert "using" in err
    # the log's own meta gives the configuration's values: the replay is the same as with a sound meta
    assert (damaged / "estimates.jsonl").read_bytes() == (out / "estimates.jsonl").read_bytes()


def test_a_missing_log_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["replay", str(tmp_path / "absent.jsonl"), "--out", str(tmp_path / "out")]) == EX_NOINPUT
    assert capsys.readouterr().err == f"robotd replay: {tmp_path / 'absent.jsonl'}: No such file or directory\n"


@pytest.mark.parametrize(
    ("name", "status"), [("nested", 0), ("reversed", EX_DATAERR), ("empty", EX_DATAERR), ("out-is-a-file", 73)]
)
def test_the_installed_command_never_prints_a_traceback(tmp_path: Path, name: str, status: int) -> None:
    lines = good_lines()
    content = {
        "nested": inserted(lines, BAD_LINES["deep nesting"]),
        "reversed": [lines[0], *reversed(lines[1:])],
        "empty": [],
        "out-is-a-file": lines,
    }[name]
    log = tmp_path / "log.jsonl"
    log.write_text("".join(content), encoding="utf-8")
    out = tmp_path / "out"
    if name == "out-is-a-file":
        out.write_text("")
    done = subprocess.run(
        [sys.executable, "-m", "robotd", "replay", str(log), "--out", str(out)],
        capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert done.returncode == status, done.stderr
    assert "Traceback" not in done.stderr
    assert len(done.stderr.splitlines()) == 1, done.stderr
