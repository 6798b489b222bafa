"""`robotd sim --robots N`: a virtual fleet, N virtual robots in one Marvelmind map, each with its own daemon, on a
Mosquitto broker started for the run.

Theory of operation. A broker is set up in `OUT/broker` (robotd.fleet.broker: a user and an ACL per robot, one for the
operator) with a fresh fleet key in `OUT/fleet.key`. Each robot `rK` gets a private copy of the simulation config in
`OUT/rK` (free ports, its own pseudo-terminal and pose socket), its own hedgehog address (10 + K) in the same map of
stationary beacons, its own start in the map (1.2 m apart), and the fleet section on; then its `robotd vhw` and
`robotd run` are started as in `robotd sim`. A thread per robot drives a 1 m square over teleop, loop after loop, so
`robotd fleet` shows them moving. On a stop signal every daemon is stopped first (motors zeroed while its virtual
pigpiod still listens), then the virtual robots, then the broker. Each process costs CPU: `robotd bench fleet` says how
many robots this machine keeps in real time.
"""

from __future__ import annotations

import base64
import contextlib
import functools
import secrets
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from robotd.config.model import load
from robotd.daemon import poseclient
from robotd.fleet.broker import OPERATOR, Broker, BrokerSetup, robot_user
from robotd.tools.demo import Children, _wait_for, private_config
from robotd.tools.teleop_client import UdpLink, run_plan, square_plan

FIRST_ADDRESS = 10
SPACING_M = 1.2
PER_ROW = 3
SQUARE_SIDE_M = 1.0
SPEED_MPS = 0.2
START_TIMEOUT_S = 30.0


class _Stopped(Exception):  # noqa: N818 - the end of the run, not an error
    """The drivers' sleep raises it once the run ends."""


@dataclass(frozen=True, slots=True)
class VirtualFleet:
    """What a person needs to watch the fleet."""

    broker_url: str
    operator_credentials: Path
    key_file: Path
    robot_ids: tuple[str, ...]
    configs: tuple[Path, ...]
    broker: Broker


def robot_ids(count: int) -> tuple[str, ...]:
    """r1, r2, ..."""
    return tuple(f"r{k}" for k in range(1, count + 1))


def start_pose(index: int) -> tuple[float, float, float]:
    """Where robot `index` (from 0) starts: rows of PER_ROW robots SPACING_M apart, in the default beacons' map."""
    return (SPACING_M * (index % PER_ROW), -1.5 * (index // PER_ROW), 0.0)


def write_fleet_key(path: Path) -> Path:
    """A fresh fleet key (32 random bytes in base64), private."""
    path.write_text(base64.b64encode(secrets.token_bytes(32)).decode() + "\n", encoding="utf-8")
    path.chmod(0o600)
    return path


def robot_config(
    base: Path, out: Path, setup: BrokerSetup, key_file: Path, *, index: int, seed: int, link: bool = True
) -> Path:
    """The private configuration of robot `index` (from 0) of the fleet."""
    robot_id = setup.robot_ids[index]
    folder = out / robot_id
    folder.mkdir(parents=True, exist_ok=True)
    pose = list(start_pose(index))
    overrides: dict[str, dict[str, object]] = {
        "sim": {"hedgehog_address": FIRST_ADDRESS + index, "initial_pose": list(pose), "seed": seed + index},
        "marvelmind": {"hedgehog_address": FIRST_ADDRESS + index},
        "ekf": {"initial_pose": list(pose)},  # a list of its own: one shared would be dumped as a YAML alias
        "fleet": {
            "enabled": link,
            "robot_id": robot_id,
            "host": "127.0.0.1",
            "port": setup.port,
            "credentials_file": str(setup.credentials_file(robot_user(robot_id))),
            "key_file": str(key_file),
        },
    }
    return private_config(base, folder, overrides)


def _driver(config_path: Path, stop: threading.Event) -> None:
    """Drive a square, loop after loop, until `stop` is set (a thread)."""
    config = load(config_path)

    def sleep(seconds: float) -> None:
        if stop.wait(seconds):
            raise _Stopped

    link = UdpLink("127.0.0.1", config.teleop.port, None)
    try:
        if not link.sync(10.0):
            return
        with contextlib.suppress(_Stopped, OSError):
            while not stop.is_set():
                run_plan(link, square_plan(SQUARE_SIDE_M, SPEED_MPS, 1, 0.5), 10.0, sleep=sleep)
    finally:
        link.close()


@contextlib.contextmanager
def virtual_fleet(
    base: Path, out: Path, count: int, seed: int = 1, *, drive: bool = True, link: bool = True
) -> Iterator[tuple[VirtualFleet, Children]]:
    """The broker, N virtual robots and their daemons running (and driving); all stopped on the way out.

    `link=False` turns the daemons' fleet link off (the benchmark's baseline): the broker then runs idle."""
    out.mkdir(parents=True, exist_ok=True)
    ids = robot_ids(count)
    setup = BrokerSetup(out / "broker", ids)
    setup.write()
    key_file = write_fleet_key(out / "fleet.key")
    configs = tuple(robot_config(base, out, setup, key_file, index=k, seed=seed, link=link) for k in range(count))
    stop = threading.Event()
    drivers: list[threading.Thread] = []
    children = Children()
    with Broker(setup) as broker:
        try:
            for config_path in configs:
                folder = config_path.parent
                device = Path(load(config_path).marvelmind.device)
                device.unlink(missing_ok=True)
                children.start(f"{folder.name} vhw", ["vhw", "--config", str(config_path)], folder / "vhw.log")
                _wait_for(device.exists, START_TIMEOUT_S, f"{folder.name}'s virtual robot", children)
            for config_path in configs:  # after every vhw: stop_all() stops the daemons first
                folder = config_path.parent
                children.start(f"{folder.name} run", ["run", "--config", str(config_path)], folder / "daemon.log")
            for config_path in configs:
                socket_path = load(config_path).pose_socket.path
                accepting = functools.partial(poseclient.accepts, socket_path)
                _wait_for(accepting, START_TIMEOUT_S, f"{config_path.parent.name}'s daemon", children)
            if drive:
                for config_path in configs:
                    driver = threading.Thread(target=_driver, args=(config_path, stop), daemon=True)
                    driver.start()
                    drivers.append(driver)
            yield VirtualFleet(setup.url, setup.credentials_file(OPERATOR), key_file, ids, configs, broker), children
        finally:
            stop.set()
            for driver in drivers:
                driver.join(2.0)
            children.stop_all()


def how_to_watch(fleet: VirtualFleet, out: Path) -> str:
    """What `robotd sim --robots N` prints: the broker, the operator's files, the commands to watch, view and stop."""
    operator = f"--broker {fleet.broker_url} --credentials {fleet.operator_credentials}"
    return "\n".join([
        f"robotd sim: {len(fleet.robot_ids)} virtual robots ({', '.join(fleet.robot_ids)}) on {fleet.broker_url}",
        f"  credentials: {fleet.operator_credentials}",
        f"  fleet key:   {fleet.key_file}",
        f"  watch:       robotd fleet {operator}",
        f"  Foxglove:    robotd fleet view {operator}    (then open ws://127.0.0.1:8765)",
        f"  stop all:    robotd fleet stop --all {operator} --key {fleet.key_file}",
        f"  logs:        {out}/rK/daemon.log, {out}/rK/vhw.log, {out}/broker/mosquitto.log",
    ])  # fmt: skip


def run_fleet_sim(base: Path, out: Path, count: int, seed: int | None) -> int:
    """`robotd sim --robots N` until a stop signal; prints what a viewer needs."""
    from robotd.tools.demo import StopRequested, stop_signals  # noqa: PLC0415

    out = out.resolve()
    try:
        with stop_signals(), virtual_fleet(base, out, count, 1 if seed is None else seed) as (fleet, children):
            print(how_to_watch(fleet, out))
            print("Ctrl-C stops them all.", flush=True)
            while all(proc.poll() is None for proc in children.procs):
                time.sleep(0.5)
            ended = [children.names[p.pid] for p in children.procs if p.poll() is not None]
            print(f"robotd sim: {', '.join(ended)} ended; stopping the fleet", flush=True)
            return 1
    except StopRequested as request:
        print(f"\nrobotd sim: {request}: the fleet and its broker are stopped", flush=True)
        return 0
    except RuntimeError as error:
        print(f"robotd sim: {error}; see the logs in {out}", file=sys.stderr)
        return 1
