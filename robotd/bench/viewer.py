"""The live view's cost: the daemon's CPU and control period while a Foxglove client watches every channel.

Theory of operation. The same run twice on the virtual robot (`robotd vhw` and `robotd run` as child processes, fixes at
16 Hz, one pose client): the daemon driving back and forth at 0.5 m/s for the same time, first without the viewer
(the baseline), then with `viewer.enabled` and one client speaking Foxglove's WebSocket protocol (the `websockets`
package, installed with robotd's test extra) subscribed to every channel the daemon advertises, reading and counting
what it receives. CPU from /proc/PID/stat over the drive; the control loop's period from the status messages (each
reports the second before it: its p99 and worst tick). Baselines: 10 % of one core (the daemon's budget), and the
control loop's worst tick with the viewer against the run without it.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from robotd.bench.daemon import (
    BENCH_OVERRIDES,
    TARGET_CPU_SHARE,
    PoseClients,
    bench_config,
    cpu_seconds,
    drive_back_and_forth,
    percentile,
    running,
)
from robotd.tools.demo import free_tcp_port
from robotd.tools.teleop_client import UdpLink

NAME = "viewer"


class ViewerClient(threading.Thread):
    """A Foxglove client in its own thread and event loop: subscribes to every channel, counts messages and bytes."""

    def __init__(self, port: int) -> None:
        super().__init__(name="foxglove-client", daemon=True)
        self.port = port
        self.messages = 0
        self.bytes = 0
        self.channels = 0
        self.subscribed = threading.Event()
        self._hang_up = threading.Event()

    def run(self) -> None:
        """Connect, subscribe, read until stopped."""
        asyncio.run(self._watch())

    async def _watch(self) -> None:
        import websockets  # noqa: PLC0415 - a test extra: only this benchmark speaks as a client

        async with websockets.connect(
            f"ws://127.0.0.1:{self.port}", subprotocols=[websockets.Subprotocol("foxglove.sdk.v1")], max_size=None
        ) as ws:
            while not self._hang_up.is_set():
                try:
                    frame = await asyncio.wait_for(ws.recv(), 0.2)
                except TimeoutError:
                    continue
                if isinstance(frame, str):
                    message = json.loads(frame)
                    if message.get("op") == "advertise":
                        subscriptions = [
                            {"id": self.channels + k + 1, "channelId": channel["id"]}
                            for k, channel in enumerate(message["channels"])
                        ]
                        self.channels += len(subscriptions)
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))
                        self.subscribed.set()
                else:
                    self.messages += 1
                    self.bytes += len(frame)

    def close(self) -> None:
        """Hang up."""
        self._hang_up.set()
        self.join(5.0)


@contextlib.contextmanager
def _watched(port: int | None) -> Iterator[ViewerClient | None]:
    if port is None:
        yield None
        return
    client = ViewerClient(port)
    client.start()
    try:
        if not client.subscribed.wait(10.0):
            raise RuntimeError("the live view advertised no channel within 10 s")
        yield client
    finally:
        client.close()


def _one_run(viewer: bool, drive_s: float) -> dict[str, float]:
    """Drive for `drive_s` with or without a watched viewer; CPU share and control period figures."""
    overrides: dict[str, dict[str, Any]] = dict(BENCH_OVERRIDES)
    port = free_tcp_port() if viewer else None
    overrides["viewer"] = {"enabled": viewer, "port": port or 8765}
    with tempfile.TemporaryDirectory(prefix="robotd-bench-") as tmp:
        out = Path(tmp)
        with running(bench_config(out, overrides), out) as (config, _vhw, daemon):
            clients = PoseClients(config.pose_socket.path, 1)
            clients.start()
            link = UdpLink("127.0.0.1", config.teleop.port, None)
            try:
                if not link.sync(5.0):
                    raise RuntimeError("the daemon did not answer the teleop hello")
                with _watched(port) as client:
                    started = time.monotonic()
                    cpu0 = cpu_seconds(daemon.pid)
                    drive_back_and_forth(link, 0.5, drive_s)
                    elapsed = time.monotonic() - started
                    cpu_share = (cpu_seconds(daemon.pid) - cpu0) / elapsed
                    received = (client.messages, client.bytes) if client is not None else (0, 0)
                periods = [m["drivers"]["control"]["period"] for m in clients.statuses if m["t"] >= started + 1.0]
                if daemon.poll() is not None:
                    raise RuntimeError(f"the daemon exited with {daemon.returncode} during the benchmark")
            finally:
                link.sock.close()
                clients.close()
    if not periods:
        raise RuntimeError("no status message while driving")
    return {
        "cpu_share": cpu_share,
        "period_p99_ms": percentile([float(p["p99_ms"]) for p in periods], 0.5),
        "period_max_ms": max(float(p["max_ms"]) for p in periods),
        "messages_per_s": received[0] / elapsed,
        "kbytes_per_s": received[1] / elapsed / 1e3,
    }


def run(quick: bool) -> dict[str, float]:
    """The daemon without and with a viewer watching every channel (see the module docstring)."""
    drive_s = 4.0 if quick else 20.0
    without = _one_run(False, drive_s)
    with_viewer = _one_run(True, drive_s)
    print(
        f"daemon CPU while driving at 0.5 m/s with a Foxglove client on every channel: "
        f"{with_viewer['cpu_share'] * 100:.1f}% of one core ({without['cpu_share'] * 100:.1f}% without the viewer); "
        f"target < {TARGET_CPU_SHARE * 100:.0f}%: ratio {with_viewer['cpu_share'] / TARGET_CPU_SHARE:.2f}"
    )
    print(
        f"control period with the viewer: p99 {with_viewer['period_p99_ms']:.1f} ms, worst "
        f"{with_viewer['period_max_ms']:.1f} ms (without: p99 {without['period_p99_ms']:.1f} ms, worst "
        f"{without['period_max_ms']:.1f} ms): worst-tick ratio "
        f"{with_viewer['period_max_ms'] / max(without['period_max_ms'], 1e-9):.2f}"
    )
    print(f"the viewer received {with_viewer['messages_per_s']:.0f} messages/s, {with_viewer['kbytes_per_s']:.0f} kB/s")
    figures = {f"without_{key}": value for key, value in without.items() if not key.startswith(("messages", "kbytes"))}
    return figures | {f"with_{key}": value for key, value in with_viewer.items()}
