"""The fleet: the daemon's CPU with the fleet link on, the fleet stop's latency, a broker outage, and how many
virtual robots this machine keeps in real time.

Theory of operation. Everything runs as `robotd sim --robots N` does (robotd.tools.fleet_sim: real `robotd vhw`,
`robotd run` and `mosquitto` processes, the robots driving squares over teleop).
- CPU: one robot driving, its daemon's CPU (/proc/PID/stat) over a window, with the fleet link on against the same
  robot with the link off (the baseline).
- Stop: two robots driving; a signed fleet stop is published and the motor pins are polled in both virtual pigpiods
  with the real `pigpio` client until every duty is zero (an upper bound, within one poll); then a release and a
  fresh drive, several times. Against the 0.2 s the issue asks.
- Outage: one robot; the broker is stopped for 30 s (5 s with --quick) and started again on the same port: the
  control loop's worst period (the daemon's status messages on its pose socket) against its nominal period, the poses
  dropped, and the time from the broker's return to the robot's next status on it.
- Real time: N robots (and their virtual robots) at once; N is sustained when every daemon's control loop keeps a p99
  period within two nominal periods and fuses at least 80 % of the fixes its virtual beacon sends (12 Hz).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import aiomqtt
import pigpio

from drivers.pigpiod.client import stop_pigpio_client
from robotd.bench.daemon import cpu_seconds
from robotd.config.model import WHEELS, load
from robotd.fleet import topics
from robotd.fleet.orders import Action, sign
from robotd.fleet.secrets import load_credentials
from robotd.tools.demo import Children
from robotd.tools.fleet_sim import VirtualFleet, virtual_fleet

NAME = "fleet"
CONFIG = Path(__file__).resolve().parents[2] / "config" / "sim.yaml"
STOP_TARGET_S = 0.2
FIX_RATE_HZ = 12.0


@contextlib.contextmanager
def _fleet(count: int, *, link: bool = True) -> Iterator[tuple[VirtualFleet, Children]]:
    with (
        tempfile.TemporaryDirectory(prefix="robotd-bench-fleet-") as tmp,
        virtual_fleet(CONFIG, Path(tmp), count, link=link) as running,
    ):
        yield running


def _pid(fleet_children: Children, name: str) -> int:
    return next(p.pid for p in fleet_children.procs if fleet_children.names[p.pid] == name)


def _daemon_cpu(window_s: float, *, link: bool) -> float:
    """Share of one core the daemon of one driving robot uses."""
    with _fleet(1, link=link) as (_fleet_info, children):
        pid = _pid(children, "r1 run")
        time.sleep(2.0)  # past start-up
        cpu0, t0 = cpu_seconds(pid), time.monotonic()
        time.sleep(window_s)
        return (cpu_seconds(pid) - cpu0) / (time.monotonic() - t0)


class _Statuses(threading.Thread):
    """Keeps the status messages of a daemon's pose socket."""

    def __init__(self, path: str) -> None:
        import socket  # noqa: PLC0415

        super().__init__(daemon=True)
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.connect(path)
        self.statuses: list[tuple[float, dict[str, Any]]] = []
        self.start()

    def run(self) -> None:
        """Read until closed."""
        with contextlib.suppress(OSError, ValueError), self.sock.makefile("r", encoding="utf-8") as stream:
            for line in stream:
                message = json.loads(line)
                if message.get("type") == "status":
                    self.statuses.append((time.monotonic(), message))

    def close(self) -> None:
        """Stop reading."""
        with contextlib.suppress(OSError):
            self.sock.shutdown(2)
        self.sock.close()
        self.join(2.0)

    def between(self, start: float, end: float) -> list[dict[str, Any]]:
        """The statuses that arrived in [start, end]."""
        return [status for arrived, status in self.statuses if start <= arrived <= end]


def _operator(fleet: VirtualFleet) -> tuple[int, str, str]:
    credentials = load_credentials(fleet.operator_credentials)
    return int(fleet.broker_url.rsplit(":", 1)[1]), credentials.username, credentials.password


async def _publish(fleet: VirtualFleet, action: Action) -> float:
    """Publish a signed fleet order; returns the monotonic time just before the publish."""
    port, user, password = _operator(fleet)
    key = fleet.key_file.read_text(encoding="utf-8").strip().encode()
    async with aiomqtt.Client("127.0.0.1", port, username=user, password=password) as client:
        payload = sign(key, action, topics.FLEET, time.time_ns(), "bench")
        started = time.monotonic()
        await client.publish(topics.FLEET_STOP, payload, qos=1, retain=True)
    return started


def _stop_latencies(repeats: int) -> list[float]:
    """Fleet stop to every motor at zero in two robots' virtual pigpiods, `repeats` times."""
    latencies: list[float] = []
    with _fleet(2) as (fleet, _children):
        configs = [load(path) for path in fleet.configs]
        pis: list[Any] = [pigpio.pi("127.0.0.1", c.pigpiod.port, show_errors=False) for c in configs]
        enables = [[getattr(c.motors.wheels, w).enable for w in WHEELS] for c in configs]

        def moving() -> bool:
            return any(pi.get_PWM_dutycycle(pin) for pi, pins in zip(pis, enables, strict=True) for pin in pins)

        def all_driving() -> bool:
            return all(any(pi.get_PWM_dutycycle(p) for p in pins) for pi, pins in zip(pis, enables, strict=True))

        try:
            for _ in range(repeats):
                _poll(all_driving, 20.0)
                published = asyncio.run(_publish(fleet, Action.STOP))
                _poll(lambda: not moving(), 5.0)
                latencies.append(time.monotonic() - published)
                asyncio.run(_publish(fleet, Action.RELEASE))
        finally:
            for pi in pis:
                stop_pigpio_client(pi)
    return latencies


def _poll(condition: Any, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise RuntimeError("timed out")
        time.sleep(0.001)


def _outage(outage_s: float) -> dict[str, float]:
    """The broker away for `outage_s`: the control loop's worst period, poses dropped, time to reconnect."""
    with _fleet(1) as (fleet, _children):
        config = load(fleet.configs[0])
        statuses = _Statuses(config.pose_socket.path)
        try:
            time.sleep(2.0)
            down = time.monotonic()
            fleet.broker.stop()
            time.sleep(outage_s)
            fleet.broker.start()
            up = time.monotonic()
            deadline = up + 30.0
            while time.monotonic() < deadline:
                time.sleep(0.1)
                latest = statuses.statuses[-1][1]["drivers"]["fleet"] if statuses.statuses else {}
                if latest.get("connected") and latest.get("connects", 0) >= 2:
                    break
            reconnected = time.monotonic() - up
            window = statuses.between(down + 1.0, up)
            worst = max((s["drivers"]["control"]["period"]["max_ms"] or 0.0) for s in window)
            dropped = statuses.statuses[-1][1]["drivers"]["fleet"]["dropped"]
        finally:
            statuses.close()
    return {"outage_s": outage_s, "worst_period_ms": worst, "poses_dropped": dropped, "reconnect_s": reconnected}


def _real_time(count: int, window_s: float) -> dict[str, float]:
    """N robots at once: each daemon's worst p99 control period and its share of the fixes sent; machine CPU."""
    with _fleet(count) as (fleet, children):
        configs = [load(path) for path in fleet.configs]
        taps = [_Statuses(c.pose_socket.path) for c in configs]
        try:
            time.sleep(3.0)
            pids = [p.pid for p in children.procs]
            cpu0, t0 = sum(cpu_seconds(pid) for pid in pids), time.monotonic()
            time.sleep(window_s)
            t1 = time.monotonic()
            cpu = (sum(cpu_seconds(pid) for pid in pids) - cpu0) / (t1 - t0)
            p99s, fix_shares = [], []
            for tap in taps:
                window = tap.between(t0, t1)
                p99s.append(max((s["drivers"]["control"]["period"]["p99_ms"] or math.inf) for s in window))
                fixes = window[-1]["filter"]["fixes"] - window[0]["filter"]["fixes"]
                fix_shares.append(fixes / (FIX_RATE_HZ * (window[-1]["t"] - window[0]["t"])))
        finally:
            for tap in taps:
                tap.close()
    return {"worst_p99_ms": max(p99s), "worst_fix_share": min(fix_shares), "cpu_cores": cpu}


def run(quick: bool) -> dict[str, float]:
    """Every figure of the module docstring."""
    window = 3.0 if quick else 10.0
    figures: dict[str, float] = {}
    on, off = _daemon_cpu(window, link=True), _daemon_cpu(window, link=False)
    print(
        f"daemon CPU, one robot driving, fleet link on: {100 * on:.1f} % of a core; link off (baseline): "
        f"{100 * off:.1f} %; the link costs {100 * (on - off):+.1f} points ({on / off:.2f}x)"
    )
    figures |= {"daemon_cpu_link_on": on, "daemon_cpu_link_off": off}
    latencies = sorted(_stop_latencies(3 if quick else 10))
    median, worst = latencies[len(latencies) // 2], latencies[-1]
    verdict = "meets" if worst <= STOP_TARGET_S else "MISSES"
    print(
        f"fleet stop to every motor at zero (2 robots, virtual pigpiods, {len(latencies)} stops): median "
        f"{1e3 * median:.0f} ms, worst {1e3 * worst:.0f} ms; target {1e3 * STOP_TARGET_S:.0f} ms: {verdict}"
    )
    figures |= {"stop_median_s": median, "stop_worst_s": worst}
    outage = _outage(5.0 if quick else 30.0)
    print(
        f"broker away {outage['outage_s']:.0f} s: worst control period {outage['worst_period_ms']:.1f} ms against "
        f"20 ms (baseline: 2 periods, 40 ms), {outage['poses_dropped']:.0f} messages dropped, reconnected "
        f"{outage['reconnect_s']:.1f} s after the broker came back"
    )
    figures |= {f"outage_{name}": value for name, value in outage.items()}
    sustained = 0
    for count in (1, 2) if quick else (1, 2, 3, 4, 6):
        result = _real_time(count, window)
        ok = result["worst_p99_ms"] <= 40.0 and result["worst_fix_share"] >= 0.8
        print(
            f"{count} virtual robot(s): worst control p99 {result['worst_p99_ms']:.1f} ms (baseline 40 ms), fixes "
            f"fused {100 * result['worst_fix_share']:.0f} % (baseline 80 %), {result['cpu_cores']:.2f} cores: "
            f"{'real time' if ok else 'NOT real time'}"
        )
        figures |= {f"robots_{count}_p99_ms": result["worst_p99_ms"], f"robots_{count}_cpu": result["cpu_cores"]}
        if not ok:
            break
        sustained = count
    print(f"virtual robots sustained in real time on this machine: {sustained}")
    figures["robots_sustained"] = float(sustained)
    return figures
