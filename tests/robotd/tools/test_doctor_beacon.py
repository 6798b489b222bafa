"""The doctor's beacon checks: the findings from what was heard, and hearing it through a real pseudo-terminal
carrying real frames, or through a running daemon's status on a real Unix socket."""

from __future__ import annotations

import json
import os
import socket
import threading
from pathlib import Path

import pytest

from drivers.marvelmind.events import Counters
from drivers.marvelmind.frames import encode_position_mm, encode_quality
from robotd.config.model import MarvelmindConfig
from robotd.tools.checklist import Finding, Verdict
from robotd.tools.doctor_beacon import BeaconSample, beacon_findings, listen_daemon, listen_serial

pytestmark = pytest.mark.timeout(30)


MARVELMIND = MarvelmindConfig()


def sample(**changes: object) -> BeaconSample:
    fields: dict[str, object] = {
        "source": "/dev/ttyACM0", "seconds": 3.0, "frames": 40, "fixes": 36, "unavailable": 1,
        "other_hedgehogs": 0, "addresses": frozenset({7}), "qualities": (90, 85),
    }  # fmt: skip
    fields.update(changes)
    return BeaconSample(**fields)  # type: ignore[arg-type]


def by_check(findings: list[Finding]) -> dict[str, Finding]:
    return {f.check: f for f in findings}


def test_a_beacon_streaming_well_passes() -> None:
    found = by_check(beacon_findings(MARVELMIND, "/dev/ttyACM0", sample()))
    assert {name: f.verdict for name, f in found.items()} == dict.fromkeys(
        ("beacon device", "beacon stream", "fix rate", "hedgehog", "quality"), Verdict.PASS
    )
    assert found["fix rate"].detail.startswith("12.0 fixes/s")
    assert found["beacon device"].detail == "/dev/marvelmind -> /dev/ttyACM0"


def test_no_device_fails_with_the_udev_fix_and_skips_the_rest() -> None:
    findings = beacon_findings(MARVELMIND, None, "no device")
    assert findings[0].verdict is Verdict.FAIL
    assert "robotd install --beacon-serial" in findings[0].fix
    assert [f.verdict for f in findings[1:]] == [Verdict.SKIP] * 4


def test_a_silent_beacon_fails() -> None:
    found = by_check(beacon_findings(MARVELMIND, "/dev/ttyACM0", sample(frames=0, fixes=0)))
    assert found["beacon stream"].verdict is Verdict.FAIL


def test_too_few_fixes_for_the_staleness_limit_fail_with_the_cause() -> None:
    lost = by_check(beacon_findings(MARVELMIND, "/dev/ttyACM0", sample(fixes=3, unavailable=30)))["fix rate"]
    assert lost.verdict is Verdict.FAIL
    assert "line of sight" in lost.fix
    slow = by_check(beacon_findings(MARVELMIND, "/dev/ttyACM0", sample(fixes=6, unavailable=0)))["fix rate"]
    assert slow.verdict is Verdict.FAIL
    assert "slower than 3.3/s" in slow.detail
    assert "marvelmind.stale_after_s to 1.0" in slow.fix


def test_the_hedgehog_address_must_be_ours() -> None:
    pinned = MarvelmindConfig(hedgehog_address=5)
    other = by_check(
        beacon_findings(pinned, "/dev/ttyACM0", sample(fixes=0, addresses=frozenset(), other_hedgehogs=30))
    )
    assert other["hedgehog"].verdict is Verdict.FAIL
    assert "no fix from address 5" in other["hedgehog"].detail
    crowded = by_check(beacon_findings(MARVELMIND, "/dev/ttyACM0", sample(other_hedgehogs=12)))["hedgehog"]
    assert crowded.verdict is Verdict.FAIL
    assert "set marvelmind.hedgehog_address to yours (7)" in crowded.fix


def test_quality_low_fails_and_absent_is_skipped_with_why() -> None:
    low = by_check(beacon_findings(MARVELMIND, "/dev/ttyACM0", sample(qualities=(90, 30))))["quality"]
    assert low.verdict is Verdict.FAIL
    assert "as low as 30 %" in low.detail
    none = by_check(beacon_findings(MARVELMIND, "/dev/ttyACM0", sample(qualities=())))["quality"]
    assert none.verdict is Verdict.SKIP
    assert "code 0x0007" in none.detail


def test_listening_to_the_serial_device_counts_fixes_addresses_and_quality(beacon_pty: tuple[int, str]) -> None:
    master, path = beacon_pty
    frames = [encode_position_mm(1000 + 100 * i, 1.0, 2.0, 0.3, 7) for i in range(6)]
    frames += [encode_position_mm(5000 + i, 0.0, 0.0, 0.0, 9) for i in range(2)]  # another hedgehog
    frames += [encode_position_mm(2000, 0.0, 0.0, 0.0, 7, flags=0x03), encode_quality(7, 77)]  # unavailable, quality
    # pyserial flushes what arrived before it opened the port (as a real port drops it): write once it listens
    writer = threading.Timer(0.1, os.write, (master, b"".join(frames)))
    writer.start()
    heard = listen_serial(path, MARVELMIND, 0.4)
    writer.join()
    assert (heard.frames, heard.fixes, heard.unavailable, heard.other_hedgehogs) == (10, 6, 1, 2)
    assert heard.addresses == frozenset({7})
    assert heard.qualities == (77,)


def status_line(t: float, counters: Counters) -> bytes:
    marvelmind = {**counters.as_dict(), "state": "streaming", "connected": True, "stale": False}
    message = {"type": "status", "t": t, "drivers": {"marvelmind": marvelmind}, "filter": {}}
    return json.dumps(message).encode() + b"\n"


def test_beside_a_running_daemon_the_beacon_is_heard_through_its_status(tmp_path: Path) -> None:
    path = str(tmp_path / "pose.sock")
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    server.bind(path)
    server.listen(1)
    before, after = Counters(), Counters()
    before.frames_by_code = {0x0011: 100, 0x0012: 1}
    after.frames_by_code = {0x0011: 136, 0x0012: 1}
    after.unavailable_fixes, after.other_address = 2, 4

    def daemon() -> None:
        client, _ = server.accept()
        with client:
            client.sendall(b'{"type":"hello"}\n{"type":"pose","t":1.0}\n')
            client.sendall(status_line(1.0, before) + status_line(2.0, before) + status_line(4.0, after))

    thread = threading.Thread(target=daemon)
    thread.start()
    heard = listen_daemon(path, 3.0, 5.0)
    thread.join()
    server.close()
    assert (heard.seconds, heard.frames, heard.fixes, heard.unavailable, heard.other_hedgehogs) == (3.0, 36, 30, 2, 4)
    found = by_check(beacon_findings(MARVELMIND, "/dev/ttyACM0", heard))
    assert found["hedgehog"].verdict is Verdict.SKIP
    assert found["quality"].verdict is Verdict.SKIP
    assert found["fix rate"].verdict is Verdict.PASS
