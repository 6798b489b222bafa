"""`robotd run --record`: the sensor log is written off the event loop, a stalled or full sink never stops the robot,
and an existing log is never overwritten."""

from __future__ import annotations

import io
import logging
import threading
from pathlib import Path

import pytest
from inprocess_daemon import FakeEncoders, FakeMotors, daemon_config, running, until

from robotd import cli
from robotd.commands import run as run_command
from robotd.daemon import recorder
from robotd.daemon.recorder import Recorder, RecorderState, RecordingError, create_log
from robotd.daemon.service import Daemon
from robotd.logs.sensorlog import Command, Event, Meta, Wheels, read_log

META = Meta(robot={"wheel_radius": 0.05}, source="test")


class StalledSink(io.StringIO):
    """A log file whose every write waits until the test releases it (a stalled disk, an NFS server gone away)."""

    def __init__(self, safety_s: float = 30.0) -> None:
        super().__init__()
        self.name = "stalled.jsonl"
        self.released = threading.Event()
        self.safety_s = safety_s  # so that a broken daemon fails the test rather than hangs it

    def write(self, text: str) -> int:
        self.released.wait(self.safety_s)
        return super().write(text)

    def close(self) -> None:
        self.lines = self.getvalue().splitlines()
        super().close()


def wheels(n: int) -> Wheels:
    return Wheels(0.02 * n, (n, n, n, n))


# --- the log file --------------------------------------------------------------------------------------------------


def test_a_recording_holds_the_meta_then_every_event_in_order(tmp_path: Path) -> None:
    stream, path = create_log(tmp_path / "run.jsonl")
    rec = Recorder(stream, META)
    rec.start()
    events: list[Event] = [wheels(1), Command(0.03, 0.1, 0.0, 0.0), wheels(2)]
    for event in events:
        rec.write(event)
    rec.close()
    log = read_log(path)
    assert log.meta.source == "test"
    assert log.events == events
    assert log.problems == []
    assert rec.counters() == {"state": "closed", "path": str(path), "written": 3, "dropped": 0}


def test_an_existing_log_is_kept_and_the_first_free_numbered_name_is_taken(tmp_path: Path) -> None:
    previous = tmp_path / "run.jsonl"
    previous.write_text('{"type": "meta"}\n', encoding="utf-8")
    (tmp_path / "run.2.jsonl").write_text("", encoding="utf-8")  # left by an older restart
    names = []
    for _ in range(3):
        stream, path = create_log(previous)
        stream.close()
        names.append(path.name)
    assert names == ["run.1.jsonl", "run.3.jsonl", "run.4.jsonl"]
    assert previous.read_text(encoding="utf-8") == '{"type": "meta"}\n'


def test_a_log_that_cannot_be_created_is_one_line_and_exit_73(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(run_command, "configure_logging", lambda verbose: None)  # keep pytest's log capture
    config = tmp_path / "robot.yaml"
    config.write_text("teleop: {key_file: '', allow_unauthenticated: true}\n", encoding="utf-8")
    (tmp_path / "a-file").write_text("", encoding="utf-8")
    status = cli.main(["run", "--config", str(config), "--record", str(tmp_path / "a-file" / "run.jsonl")])
    err = capsys.readouterr().err
    assert status == 73
    assert err.startswith("robotd run: --record: cannot create the folder of ")
    assert len(err.strip().splitlines()) == 1
    assert "Traceback" not in err


def test_every_numbered_name_taken_is_a_clear_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(recorder, "MAX_NUMBERED", 2)
    for name in ("log.jsonl", "log.1.jsonl", "log.2.jsonl"):
        (tmp_path / name).touch()
    with pytest.raises(RecordingError, match=r"log\.jsonl and log\.1\.jsonl to \.2\.jsonl all exist"):
        create_log(tmp_path / "log.jsonl")


# --- a sink that stalls or fails --------------------------------------------------------------------------------------


def test_a_stalled_sink_never_blocks_the_caller_and_what_does_not_fit_is_dropped_and_counted() -> None:
    sink = StalledSink()
    rec = Recorder(sink, META, capacity=8)
    rec.start()
    for n in range(100):  # would wait on the stalled sink 100 times if written by the caller
        rec.write(wheels(n))
    assert 100 - 9 <= rec.dropped < 100, "the queue holds 8 events (+1 slot for the meta line), the rest is dropped"
    assert rec.written == 0
    sink.released.set()
    rec.close()
    assert rec.written + rec.dropped == 100
    assert len(sink.lines) == 1 + rec.written


def test_closing_on_a_stalled_sink_gives_up_after_its_timeout_and_says_what_was_left(
    caplog: pytest.LogCaptureFixture,
) -> None:
    sink = StalledSink()
    rec = Recorder(sink, META, capacity=4)
    rec.start()
    while rec._queue.qsize():  # the thread has taken the meta line and waits on the sink with it
        threading.Event().wait(0.001)
    for n in range(10):
        rec.write(wheels(n))
    rec.close(timeout_s=0.1)  # the daemon's shutdown (motors already zeroed) must not hang on the log
    assert rec._thread.is_alive()
    assert [r.getMessage() for r in caplog.records] == [
        "recording: stalled.jsonl did not accept the last 5 events within 0.1 s; left unwritten"
    ]
    sink.released.set()  # the sink wakes up later: the thread writes what it holds and leaves
    rec._thread.join(10.0)
    assert not rec._thread.is_alive()
    assert len(sink.lines) == 1 + 5


def test_a_full_disk_stops_the_recording_with_one_error_line_and_nothing_raises(
    caplog: pytest.LogCaptureFixture,
) -> None:
    full = Path("/dev/full").open("w", encoding="utf-8")  # noqa: SIM115 - the recorder owns and closes it
    rec = Recorder(full, META)
    rec.start()
    rec.write(wheels(1))
    rec._thread.join(10.0)  # the thread leaves after the failure
    assert rec.state is RecorderState.FAILED
    for n in range(10):
        rec.write(wheels(n))
    rec.close()
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1
    assert errors[0].getMessage().startswith("recording stopped: cannot write /dev/full: No space left on device")
    assert errors[0].exc_info is None
    assert rec.dropped >= 10


def test_an_unexpected_error_in_the_writer_is_logged_with_its_traceback(caplog: pytest.LogCaptureFixture) -> None:
    class Broken(io.StringIO):
        def write(self, text: str) -> int:
            raise RuntimeError("a bug in the sink")

    rec = Recorder(Broken(), META)
    rec.start()
    rec.close()
    assert rec.state is RecorderState.FAILED
    assert [(r.levelno, r.exc_info is not None) for r in caplog.records] == [(logging.ERROR, True)]


# --- the daemon with a recorder -------------------------------------------------------------------------------------


async def test_a_stalled_record_sink_does_not_stop_the_control_loop(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(recorder, "QUEUE_EVENTS", 16)
    sink = StalledSink()
    encoders = FakeEncoders(lambda: 0.0, period_s=0.005)
    daemon = Daemon(daemon_config(tmp_path), record=sink, encoders=encoders, motors_factory=FakeMotors)
    steps = daemon._counters
    try:
        async with running(daemon) as task:
            await until(lambda: steps["control_steps"] > 0, "the control loop to start")
            started = steps["control_steps"]
            # 100 control steps, each with encoder samples to record, while not one line could be written
            await until(lambda: steps["control_steps"] >= started + 100, "control steps with the sink stalled", 60.0)
            status = daemon._status_message(0.0)
            assert not task.done()
            sink.released.set()
    finally:
        sink.released.set()
    assert status["drivers"]["recorder"]["written"] == 0
    assert status["drivers"]["recorder"]["dropped"] > 0, "the queue overflowed: the drops are counted in the status"
    assert len(sink.lines) >= 1 + 16, "the meta line and the queued events were written once the sink woke up"


async def test_a_record_sink_that_fails_stops_recording_and_the_daemon_keeps_running(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    full = Path("/dev/full").open("w", encoding="utf-8")  # noqa: SIM115 - the daemon's recorder closes it
    daemon = Daemon(daemon_config(tmp_path), record=full, encoders=FakeEncoders(lambda: 0.0), motors_factory=FakeMotors)
    steps = daemon._counters
    async with running(daemon) as task:
        await until(lambda: daemon._status_message(0.0)["drivers"]["recorder"]["state"] == "failed", "the failure")
        failed_at = steps["control_steps"]
        await until(lambda: steps["control_steps"] >= failed_at + 20, "control steps after the failure")
        assert not task.done()
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert [r.getMessage().split(":")[0] for r in errors] == ["recording stopped"]
