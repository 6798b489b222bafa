"""Replays as MCAP and scrubbable views: `robotd replay --mcap` writes every method and the truth; the player serves
an MCAP file with playback controls that a real client drives (play, seek)."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest
from foxglove_client import FoxgloveClient, playback_request
from mcap.reader import make_reader
from sim_logs import sim_config, simulated_text

from robotd.cli import main
from robotd.logs.sensorlog import read_log
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
