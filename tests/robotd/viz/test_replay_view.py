"""Replays as MCAP and scrubbable views: `robotd replay --mcap` writes every method and the truth; the player serves
an MCAP file with playback controls that a real client drives (play, seek)."""

from __future__ import annotations

import itertools
import math
import threading
from pathlib import Path

import pytest
from foxglove_client import FoxgloveClient, playback_request, protobuf_class
from mcap.reader import make_reader
from sim_logs import sim_config, simulated_text

from robotd.cli import main
from robotd.logs.sensorlog import Truth, read_log
from robotd.viz.mcaplog import read_mcap_log
from robotd.viz.player import McapPlayer


@pytest.fixture(scope="module")
def replayed(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A simulated square replayed with --mcap: (the log, the MCAP file)."""
    folder = tmp_path_factory.mktemp("replay")
    log = folder / "square.jsonl"
    log.write_text(simulated_text(sim_config(), seed=3), encoding="utf-8")
    mcap = folder / "replay.mcap"
    assert main(["replay", str(log), "--out", str(folder / "out"), "--mcap", str(mcap)]) == 0
    return log, mcap


def test_replay_writes_the_log_every_method_and_the_truth_as_mcap(replayed: tuple[Path, Path]) -> None:
    log, mcap = replayed
    with mcap.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    assert summary.statistics is not None
    counts = {summary.channels[c].topic: n for c, n in summary.statistics.channel_message_counts.items()}
    for topic in ("/pose", "/pose/odometry", "/replay/paper_ekf/pose", "/replay/odometry/pose", "/replay/truth/pose"):
        assert counts.get(topic, 0) > 100, topic
    assert read_mcap_log(mcap).events == read_log(log).events, "the replay's MCAP replays again"


def test_a_replays_trails_reach_back_as_far_as_the_live_views(tmp_path: Path) -> None:
    # each trail is sent whole every second: one of the whole log made the file grow with the square of its length
    log = tmp_path / "square.jsonl"
    log.write_text(simulated_text(sim_config(), seed=3), encoding="utf-8")
    config = tmp_path / "robotd.yaml"
    config.write_text("viewer:\n  trail_s: 5.0\n", encoding="utf-8")
    mcap = tmp_path / "replay.mcap"
    argv = ["replay", str(log), "--out", str(tmp_path / "out"), "--mcap", str(mcap), "--config", str(config)]
    assert main(argv) == 0
    truth = [(e.t, e.x, e.y) for e in read_log(log).events if isinstance(e, Truth)]
    top_speed = max(
        math.hypot(x1 - x0, y1 - y0) / (t1 - t0) for (t0, x0, y0), (t1, x1, y1) in itertools.pairwise(truth)
    )
    with mcap.open("rb") as stream:
        trails = [(schema, message) for schema, channel, message in make_reader(stream).iter_messages()
                  if channel.topic == "/replay/truth/trail"]  # fmt: skip
    assert len(trails) > 20, "a trail a second over the whole log"
    schema, last = trails[-1]
    assert schema is not None
    poses = protobuf_class(schema.name, schema.data).FromString(last.data).poses
    path = sum(
        math.hypot(b.position.x - a.position.x, b.position.y - a.position.y) for a, b in itertools.pairwise(poses)
    )
    assert 0.0 < path <= top_speed * 5.0 + 0.02, "the trail holds the last 5 s of the drive, not all of it"


async def test_the_player_serves_a_replay_with_playback_controls_and_seeks(replayed: tuple[Path, Path]) -> None:
    _, mcap = replayed
    player = McapPlayer(mcap)
    port = player.serve("127.0.0.1", 0)
    stop = threading.Event()
    pacing = threading.Thread(target=player.run, args=(stop,))
    pacing.start()
    client = await FoxgloveClient.open(port)
    try:
        await client.subscribe(["/pose", "/replay/truth/pose"])
        assert "playbackControl" in client.server_info["capabilities"]
        middle = (player.start_ns + player.end_ns) // 2
        await client.ws.send(playback_request(True, 20.0, middle, "seek-1"))
        got = await client.collect({"/pose": 5, "/replay/truth/pose": 5})
        first = min(r.log_time for r in got["/pose"])
        assert first >= middle, "playback starts where the client seeked"
    finally:
        await client.close()
        stop.set()
        pacing.join()
        player.stop()
    _, time_ns, speed = player.state()
    assert speed == 20.0
    assert time_ns > middle
    assert player.sent > 0
