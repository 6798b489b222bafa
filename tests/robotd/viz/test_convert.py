"""JSON Lines <-> MCAP: lossless both ways, bad lines reported and skipped, record types derived from the format."""

from __future__ import annotations

import math
from pathlib import Path

import msgspec
import pytest

from robotd.cli import main
from robotd.logs import events
from robotd.logs.sensorlog import read_log
from robotd.viz import logtopics
from robotd.viz.mcaplog import log_lines, read_mcap_log, write_mcap_log

LOG = """\
{"type":"meta","robot":{"wheel_radius":0.05},"source":"test","format":"robotd-log","version":1}
{"type":"wheels","t":0.02,"ticks":[1,2,3,4]}
{"type":"ips","t":0.061,"x":1.2,"y":0.4,"z":0.0,"t_meas":0.04}
{"type":"wheels","t":0.04,"ticks":[5,6,7,8]}
{"type":"ips_lost","t":0.07}
{"type":"truth","t":0.08,"x":1.19,"y":0.41}
{"type":"cmd","t":0.09,"vx":0.3,"vy":0.0,"wz":0.0}
{"type":"twist","t":0.1,"vx":0.2,"vy":0.0,"wz":0.1}
"""


def test_json_lines_to_mcap_and_back_gives_the_same_bytes_and_keeps_the_arrival_order(tmp_path: Path) -> None:
    source, mcap, back = tmp_path / "a.jsonl", tmp_path / "a.mcap", tmp_path / "b.jsonl"
    source.write_text(LOG, encoding="utf-8")
    assert main(["convert-log", str(source), str(mcap)]) == 0
    assert main(["convert-log", str(mcap), str(back)]) == 0
    assert back.read_text(encoding="utf-8") == LOG
    # the fix arrived (t 0.061) before the wheel sample stamped 0.04: the log's order, not t's, is kept
    assert [e.t for e in read_mcap_log(mcap).events][:3] == [0.02, 0.061, 0.04]
    truth = read_mcap_log(mcap).events[4]
    assert isinstance(truth, events.Truth)
    assert math.isnan(truth.theta)


def test_a_bad_line_is_reported_and_skipped_and_the_rest_converted(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    source, mcap = tmp_path / "a.jsonl", tmp_path / "a.mcap"
    source.write_text(LOG + '{"type":"wheels","t":"soon"}\n{"type":"calibration","t":1.0}\n', encoding="utf-8")
    assert main(["convert-log", str(source), str(mcap)]) == 0
    out, err = capsys.readouterr()
    assert "line 9" in err
    assert "(unknown types skipped: 1 calibration)" in out
    assert read_mcap_log(mcap).events == read_log(source).events


def test_a_file_that_is_not_mcap_is_one_line_and_exit_66(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"not an mcap file")
    assert main(["convert-log", str(bad), str(tmp_path / "out.jsonl")]) == 66
    assert "not a readable MCAP file" in capsys.readouterr().err
    assert main(["replay", str(bad), "--out", str(tmp_path / "r")]) == 66


class Calibration(msgspec.Struct, frozen=True, tag="calibration"):
    """A record type the filter may add to the log format."""

    t: float
    latency_s: float


def test_a_record_type_added_to_the_format_gets_its_channel_without_an_edit(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(events, "Record", events.Record | Calibration)
    topics = logtopics.record_topics()
    assert topics["calibration"].topic == "/log/calibration"
    assert topics["calibration"].schema["properties"]["latency_s"] == {"type": "number"}
    assert set(topics) == {"meta", "wheels", "twist", "ips", "ips_lost", "truth", "cmd", "calibration"}
    path = tmp_path / "c.mcap"
    write_mcap_log([events.Meta(), Calibration(1.5, 0.12)], path)  # type: ignore[list-item]
    assert log_lines(path)[-1] == b'{"type":"calibration","t":1.5,"latency_s":0.12}'
