"""The virtual fleet end to end: real `robotd vhw` and `robotd run` processes, a real mosquitto, the real clients.

One run checks what needs real processes: both poses on the broker match each daemon's pose socket, a fleet stop
brings every motor to zero as the virtual pigpiod sees it (measured, not asserted beyond a generous bound), and a
daemon killed with SIGKILL is announced `offline` by the broker's last will.
"""

from __future__ import annotations

import asyncio
import json
import signal
import threading
import time
from pathlib import Path
from typing import Any

import pigpio
import pytest
from daemon_support import PoseTap, channel_duty
from fleet_support import watcher_at
from inprocess_daemon import until
from mosquitto import require_mosquitto
from paths import REPO

from drivers.pigpiod.client import stop_pigpio_client
from robotd.config.model import WHEELS, load
from robotd.fleet import topics
from robotd.fleet.orders import Action
from robotd.kinematics import Twist
from robotd.tools.fleet_sim import virtual_fleet
from robotd.tools.teleop_client import UdpLink

pytestmark = pytest.mark.slow


class Driver(threading.Thread):
    """Sends one robot a forward command at 20 Hz until closed."""

    def __init__(self, teleop_port: int) -> None:
        super().__init__(daemon=True)
        self.link = UdpLink("127.0.0.1", teleop_port, None)
        self.done = threading.Event()
        self.start()

    def run(self) -> None:
        """Command 0.2 m/s forward until closed."""
        self.link.sync(10.0)
        while not self.done.wait(0.05):
            self.link.send(Twist(0.2, 0.0, 0.0))

    def close(self) -> None:
        """Stop sending."""
        self.done.set()
        self.join(2.0)
        self.link.close()


async def test_a_virtual_fleet_on_one_broker(tmp_path: Path) -> None:
    require_mosquitto()
    with virtual_fleet(REPO / "config" / "sim.yaml", tmp_path / "fleet", 2, drive=False) as (fleet, children):
        key = (fleet.key_file.read_text(encoding="utf-8").strip()).encode()
        configs = [load(path) for path in fleet.configs]
        taps = [PoseTap(config.pose_socket.path) for config in configs]
        pis: list[Any] = [pigpio.pi("127.0.0.1", c.pigpiod.port, show_errors=False) for c in configs]
        pins = [[getattr(c.motors.wheels, wheel) for wheel in WHEELS] for c in configs]

        def duties(k: int) -> list[float]:
            return [channel_duty(pis[k], p) for p in pins[k]]

        drivers: list[Driver] = []
        try:
            password = fleet.operator_credentials.read_text(encoding="utf-8").strip().partition(":")[2]
            async with watcher_at(int(fleet.broker_url.rsplit(":", 1)[1]), password) as watching:
                await until(lambda: all(len(watching.on(topics.pose(r))) >= 5 for r in fleet.robot_ids), "poses", 20)
                for robot_id, tap in zip(fleet.robot_ids, taps, strict=True):
                    by_t = {pose["t"]: pose for _arrived, pose in tap.poses}
                    matched = [p for p in watching.on(topics.pose(robot_id)) if p["t"] in by_t]
                    assert len(matched) >= 3
                    assert all(p == json.loads(json.dumps(by_t[p["t"]])) for p in matched)
                drivers = [Driver(c.teleop.port) for c in configs]
                await until(lambda: all(any(duties(k)) for k in range(2)), "both robots driving", 20)
                published = time.monotonic()
                await watching.publish_order(key, Action.STOP, topics.FLEET)
                await until(lambda: not any(any(duties(k)) for k in range(2)), "every motor at zero", 5.0)
                latency = time.monotonic() - published
                print(
                    f"\nfleet stop to every motor at zero in the virtual pigpiods: {latency * 1e3:.0f} ms (upper bound)"
                )
                await asyncio.sleep(0.5)  # the drivers keep commanding: the stop holds
                assert not any(any(duties(k)) for k in range(2))
                daemon = next(p for p in children.procs if children.names[p.pid] == "r1 run")
                killed = time.monotonic()
                daemon.send_signal(signal.SIGKILL)
                keepalive = configs[0].fleet.keepalive_s

                def offline() -> bool:
                    statuses = watching.on(topics.status("r1"))
                    return bool(statuses) and statuses[-1]["state"] == "offline"

                await until(offline, "r1's last will", 1.5 * keepalive + 5.0)
                print(f"last will 'offline' {time.monotonic() - killed:.2f} s after SIGKILL (keep-alive {keepalive} s)")
                assert watching.on(topics.status("r2"))[-1]["state"] == "online"
        finally:
            for driver in drivers:
                driver.close()
            for tap in taps:
                tap.close()
            for pi in pis:
                stop_pigpio_client(pi)
