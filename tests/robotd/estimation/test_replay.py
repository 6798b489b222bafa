"""`robotd replay` end to end: synthetic logs with known truth, the CLI's files, bad lines, and the libRSF data."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from robotd import cli, librsf, synthlog
from robotd.config import parse
from robotd.logfile import LogWriter, SensorLog, read_log
from robotd.replay import replay

SHARED = Path(__file__).resolve().parents[3].parent / "shared"
LIBRSF = SHARED / "datasets" / "librsf_labyrinth_uwb"

# Realistic Marvelmind timing: 4-16 Hz, 30-150 ms latency, 2-4 cm noise, 1-3 m outlier bursts, outages of seconds.
LOGS = [
    (11, synthlog.SynthSpec(loops=1, fix_rate_hz=4.0, noise_m=0.04, outlier_bursts_per_min=6.0, outage_s=5.0)),
    (12, synthlog.SynthSpec(loops=1, fix_rate_hz=16.0, noise_m=0.02, ips_offset_m=(0.1, 0.05))),
    (13, synthlog.SynthSpec(loops=1, fix_rate_hz=8.0, noise_m=0.03, outlier_bursts_per_min=4.0, outages=2)),
]


@pytest.mark.parametrize(("seed", "spec"), LOGS)
def test_robotd_beats_odometry_fixes_and_the_paper_on_every_log(seed: int, spec: synthlog.SynthSpec) -> None:
    meta, events = synthlog.generate(spec, seed)
    result = replay(SensorLog(meta=meta, events=events), parse(""))
    assert result.metrics is not None
    ours = result.metrics["ekf"]
    assert ours is not None
    for other in ("odometry", "ips", "paper_ekf"):
        theirs = result.metrics[other]
        assert theirs is not None
        assert ours.rmse_m < theirs.rmse_m, other
        assert ours.max_m < theirs.max_m, other
    # the largest errors come at the end of multi-second outages, where only odometry (and its heading drift) is left
    assert ours.rmse_m < spec.noise_m + 0.01
    assert ours.max_m < 0.2


def _write(path: Path, meta_and_events: tuple[object, list[object]], extra: list[str]) -> None:
    meta, events = meta_and_events
    with open(path, "w", encoding="utf-8") as stream:
        writer = LogWriter(stream, meta)  # type: ignore[arg-type]
        for event in events:
            writer.write(event)  # type: ignore[arg-type]
        stream.writelines(extra)


def test_the_command_writes_causal_estimates_and_metrics_and_reports_bad_lines(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log = tmp_path / "drive.jsonl"
    meta, events = synthlog.generate(synthlog.SynthSpec(loops=1, side_m=1.0), 3)
    _write(log, (meta, list(events)), ["{not json\n", '{"t": 99.0, "type": "lidar", "ranges": []}\n'])
    status = cli.main(["replay", str(log), "--out", str(tmp_path / "out")])
    assert status == 0
    out = capsys.readouterr()
    assert f"line {len(events) + 2}" in out.err  # the meta line is line 1
    assert "lidar x1" in out.out
    lines = (tmp_path / "out" / "estimates.jsonl").read_text().splitlines()
    estimates = [json.loads(line) for line in lines]
    assert len(estimates) > 100
    assert set(estimates[0]) == {"t", "x", "y", "theta", "cov"}
    assert len(estimates[0]["cov"]) == 9
    times = [e["t"] for e in estimates]
    assert times == sorted(times)
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert set(metrics) == {"odometry", "ips", "paper_ekf", "ekf"}
    for entry in metrics.values():
        assert {"rmse_m", "max_m", "final_m"} <= set(entry)


def test_meta_robot_overrides_the_configured_geometry(tmp_path: Path) -> None:
    meta, events = synthlog.generate(synthlog.SynthSpec(loops=1, side_m=1.0, ips_offset_m=(0.1, 0.0)), 4)
    config = parse("robot: {wheel_radius_m: 0.05, ips_offset_m: [0.0, 0.0]}\nencoders: {ppr: 100}")
    result = replay(SensorLog(meta=meta, events=events), config)
    assert result.geometry.wheel_radius_m == meta.robot["wheel_radius"]
    assert result.counts_per_rev == 6800
    assert result.ips_offset == (0.1, 0.0)


@pytest.mark.skipif(not LIBRSF.is_dir(), reason="the shared libRSF dataset is not beside the repository")
def test_librsf_real_data_beats_its_dead_reckoning_and_its_fixes(tmp_path: Path) -> None:
    out = tmp_path / "librsf.jsonl"
    assert cli.main(["convert-librsf", str(LIBRSF), "--out", str(out)]) == 0
    log = read_log(out)
    assert log.problems == []
    assert "Tim Pfeifer" in log.meta.source
    assert "CC BY-SA 4.0" in log.meta.source
    result = replay(log, parse(""))
    assert result.metrics is not None
    ours = result.metrics["ekf"]
    fixes = result.metrics["ips"]
    odometry = result.metrics["odometry"]
    assert ours is not None
    assert fixes is not None
    assert odometry is not None
    assert ours.heading_rmse_deg is None  # the dataset has no heading truth
    assert ours.mean_m < 0.20  # the dataset's dead reckoning, mean error (its README)
    assert ours.median_m < 0.17  # its fixes, median error (its README)
    assert ours.rmse_m < min(fixes.rmse_m, odometry.rmse_m)


def test_convert_librsf_reports_a_missing_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["convert-librsf", str(tmp_path / "nowhere"), "--out", str(tmp_path / "x.jsonl")]) == 1
    assert "cannot read" in capsys.readouterr().err
    with pytest.raises(librsf.DatasetError):
        librsf.convert(tmp_path)
