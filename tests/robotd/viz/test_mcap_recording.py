"""MCAP recordings: the daemon records one run as JSON Lines and as MCAP; the MCAP, read back with the `mcap`
reader, replays exactly as the JSON Lines log does, and it holds what the daemon published."""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path

from inprocess_daemon import FakeMotors, daemon_config, running, until
from mcap.reader import make_reader
from viz_support import RollingEncoders, fix

from robotd.config.model import parse
from robotd.daemon.service import Daemon
from robotd.logs.sensorlog import read_log
from robotd.offline.replay import replay
from robotd.viz.mcaplog import read_mcap_log


async def record_one_run(tmp_path: Path, *, serve: bool) -> tuple[Path, Path]:
    """A short drive with fixes, recorded both ways; the daemon stopped (files closed)."""
    jsonl, mcap = tmp_path / "run.jsonl", tmp_path / "run.mcap"
    config = daemon_config(tmp_path, viewer={"enabled": serve, "port": 0})
    with jsonl.open("x", encoding="utf-8") as stream:
        daemon = Daemon(config, record=stream, record_mcap=mcap, encoders=RollingEncoders(time.monotonic),
                        motors_factory=FakeMotors)  # fmt: skip
        async with running(daemon):
            await until(lambda: daemon.estimator.counters["wheels"] > 5, "wheel samples")
            for k in range(8):
                fix(daemon, 0.01 * k, 0.0)
                await asyncio.sleep(0.05)
            await until(lambda: daemon.estimator.counters["wheels"] > 40, "more wheel samples")
    return jsonl, mcap


async def test_a_replay_of_the_mcap_recording_equals_a_replay_of_the_json_lines_log_of_the_same_run(
    tmp_path: Path,
) -> None:
    jsonl, mcap = await record_one_run(tmp_path, serve=False)
    from_jsonl, from_mcap = read_log(jsonl), read_mcap_log(mcap)
    assert len(from_jsonl.events) > 40
    assert from_mcap.events == from_jsonl.events
    assert from_mcap.meta == from_jsonl.meta
    config = parse("")
    a, b = replay(from_jsonl, config), replay(from_mcap, config)
    assert a.diagnostics == b.diagnostics
    assert a.diagnostics, "the fixes were judged"
    assert list(a.ekf.x) == list(b.ekf.x)
    assert list(a.ekf.y) == list(b.ekf.y)
    assert a.ekf_cov.tolist() == b.ekf_cov.tolist()


async def test_the_mcap_recording_holds_what_the_daemon_published_beside_the_log(tmp_path: Path) -> None:
    _, mcap = await record_one_run(tmp_path, serve=True)
    with mcap.open("rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert summary is not None
        assert summary.statistics is not None
        topics = {channel.topic for channel in summary.channels.values()}
        counts = {
            summary.channels[channel_id].topic: n for channel_id, n in summary.statistics.channel_message_counts.items()
        }
        schemas = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
        verdicts = [json.loads(m.data) for _, _, m in reader.iter_messages(topics=["/ips/verdicts"])]
    assert {"/pose", "/pose/odometry", "/tf", "/ips/fixes", "/log/wheels", "/log/ips", "/log/meta"} <= topics
    assert counts["/pose"] > 0
    assert counts["/log/ips"] == 8
    assert schemas["/pose"] == "foxglove.PoseInFrame"
    assert schemas["/log/wheels"] == "robotd.log.wheels"
    assert [v["verdict"] for v in verdicts][-1] in ("seeded", "accepted")
