"""`robotd doctor`: check a freshly wired robot, one line a check; exit 0 when nothing failed, 1 otherwise."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import sys
from typing import TextIO

from robotd.config.model import WHEELS, load
from robotd.config.schema import ConfigError
from robotd.tools.checklist import Finding, exit_status, summary
from robotd.tools.doctor_spin import Ask, Seen, SpinPlan
from robotd.tools.gpio_backend import BACKEND_NAMES

DEFAULT_CONFIG = "/etc/robotd/robot.yaml"
DEFAULT_DUTY = 0.5
ANSWERS = {"f": Seen.FORWARD, "b": Seen.BACKWARD, "n": Seen.STILL}


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `robotd doctor`."""
    doctor = subparsers.add_parser(
        "doctor", help="check a freshly wired robot: GPIO, pins, beacon, key, service, clock; --spin each wheel"
    )
    doctor.add_argument("--config", default=DEFAULT_CONFIG, help=f"configuration (default {DEFAULT_CONFIG})")
    doctor.add_argument(
        "--spin", action="store_true", help="drive each wheel in turn and read the encoders (wheels off the ground!)"
    )
    doctor.add_argument(
        "--spin-duty", type=float, default=DEFAULT_DUTY, metavar="D", help="duty of each wheel's spin (default 0.5)"
    )
    doctor.add_argument(
        "--seen",
        nargs=4,
        choices=sorted(ANSWERS),
        metavar=("FL", "FR", "RL", "RR"),
        help="which way each wheel turned, as you saw it: f(orward), b(ackward), n(ot at all); asked in a terminal",
    )
    doctor.add_argument(
        "--beacon-seconds", type=float, default=3.0, metavar="S", help="how long to listen to the beacon (default 3)"
    )
    doctor.add_argument(
        "--backend", choices=BACKEND_NAMES, help="GPIO back-end (default: the configuration's gpio.backend)"
    )
    doctor.set_defaults(handler=run_doctor)


def ask_person(stdin: TextIO, prompt: TextIO) -> Ask:
    """Ask after each wheel which way it turned; an empty answer or the end of input means nobody watched."""

    async def ask(wheel: str) -> Seen:
        prompt.write(f"{wheel}: which way did it turn? [f]orward, [b]ackward, [n]ot at all, Enter: did not watch: ")
        prompt.flush()
        answer = (await asyncio.to_thread(stdin.readline)).strip().lower()[:1]
        return ANSWERS.get(answer, Seen.UNSEEN)

    return ask


def answers_given(seen: list[str]) -> Ask:
    """The person's observations, given on the command line."""
    by_wheel = dict(zip(WHEELS, (ANSWERS[s] for s in seen), strict=True))

    async def ask(wheel: str) -> Seen:
        return by_wheel[wheel]

    return ask


def _print(finding: Finding) -> None:
    for line in finding.lines():
        print(line, flush=True)


def run_doctor(args: argparse.Namespace) -> int:
    """Run the checklist and print it; 0 when nothing failed."""
    from drivers.wheels.motors import termination_as_exit  # noqa: PLC0415 - keeps `robotd --help` fast
    from robotd.tools.doctor import DoctorOptions, Host, examine  # noqa: PLC0415

    if not 0.05 <= args.spin_duty <= 1.0:
        print(f"robotd doctor: --spin-duty must be within 0.05 and 1, got {args.spin_duty}", file=sys.stderr)
        return 2
    ask = None
    if args.spin and args.seen:
        ask = answers_given(args.seen)
    elif args.spin and sys.stdin.isatty():
        ask = ask_person(sys.stdin, sys.stderr)
        print(
            "Lift the robot: no wheel may touch the ground. Enter to start, Ctrl-C to stop: ", end="", file=sys.stderr
        )
        sys.stdin.readline()
    options = DoctorOptions(
        args.config,
        backend=args.backend,
        beacon_s=args.beacon_seconds,
        spin=SpinPlan(duty=args.spin_duty) if args.spin else None,
        ask=ask,
    )
    print(f"robotd doctor: {args.config}", flush=True)
    try:
        with termination_as_exit():
            findings = asyncio.run(examine(options, Host(), _print, lambda text: print(f"      {text}", flush=True)))
    finally:
        if args.spin:
            _stop_motors(args.config, args.backend)
    print(f"robotd doctor: {summary(findings)}")
    return exit_status(findings)


def _stop_motors(config_path: str, backend_name: str | None) -> None:
    """The last word after a spin, whatever happened (Ctrl-C, SIGTERM): every motor off through the back-end."""
    from robotd.config.gpio import resolve_backend  # noqa: PLC0415
    from robotd.tools.gpio_backend import BackendUnavailableError, backends  # noqa: PLC0415

    with contextlib.suppress(ConfigError, BackendUnavailableError):  # then nothing was spun
        config = load(config_path)
        backends()[backend_name or resolve_backend(config.gpio)].open_drive(config).close()
