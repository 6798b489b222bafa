"""The daemon: one asyncio TaskGroup owning every long-lived task, motors zeroed on every way out.

Theory of operation. Producers call back into the daemon from the loop (no threads): the encoder source hands
`WheelTicks` at its publish rate (-> estimator prediction, wheel speeds for the control loop, the sensor log), the
Marvelmind reader hands parser events (-> estimator update, and a pose published at once so a fix reaches the pose
socket without waiting for the next period; what the filter learns from the fix waits for the next input), and the
teleop socket hands validated commands (-> while the wheels are not driven the control loop is woken at once, so a
command that starts them reaches the motors without waiting for the next period; while they are, the loop reads the
socket itself at each period). The control loop steps the `MotionController` at `control.rate_hz` and writes the duties;
the pose task publishes at `pose_socket.rate_hz` and a status at 1 Hz; the health task pings systemd's watchdog only
while the control loop and the filter keep ticking.

Exit paths: SIGTERM, SIGINT, SIGHUP or SIGQUIT ends the TaskGroup and `run()` returns 0; an exception in any task
cancels the others and `run()` returns 1 (systemd restarts the service). Either way the motors are zeroed before
anything else is torn down, and the deadman script is removed from pigpiod. A failure that is operational (a device
or pigpiod gone) is logged in one line, any other (a bug) at ERROR with its traceback. The deadman
(drivers.pigpiod.deadman) covers the ways out no handler sees: SIGKILL, SIGSTOP, a hung loop. Installed in pigpiod
with the motors, bumped by the control loop a few times per timeout, it stops the motors `teleop.deadman_timeout_s`
after the last bump; when it did, the daemon writes every motor pin again and drives only after a fresh command. A
pigpiod that goes away (or a deadman that is lost) is re-connected with backoff, motors and deadman together; the
motors are driven again only after a command that arrived after the reconnection.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import math
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

import pigpio

from drivers.backoff import Backoff
from drivers.marvelmind.events import Event as MarvelmindEvent
from drivers.marvelmind.events import FixUnavailable, Position, StationaryBeacons
from drivers.marvelmind.reader import MarvelmindReader
from drivers.pacing import next_tick, sleep_until
from drivers.pigpiod.client import PigpioCommandError
from drivers.pigpiod.protocol import ProtocolError
from drivers.wheels.encoders import EncoderSource, WheelTicks
from drivers.wheels.motors import MotorOutputs
from robotd.config.model import RobotdConfig
from robotd.daemon import calibration_store, posesock
from robotd.daemon.control import ControlState, MotionController, StallFault
from robotd.daemon.deadman_keeper import DeadmanFactory, DeadmanKeeper
from robotd.daemon.hardware import Hardware, build_hardware
from robotd.daemon.pacer import ControlPacer
from robotd.daemon.periodstats import PeriodStats
from robotd.daemon.recorder import Recorder, create_log, daemon_meta
from robotd.daemon.sdnotify import Notifier
from robotd.daemon.teleop import StopCommand, TeleopMessage, receiver_from_config
from robotd.daemon.teleop_socket import TeleopSocket, open_teleop
from robotd.estimation.estimator import Estimator
from robotd.fleet.hook import fleet_link
from robotd.kinematics import Geometry, Twist
from robotd.logs import sensorlog
from robotd.viz import live

log = logging.getLogger("robotd")

ZERO = (0.0, 0.0, 0.0, 0.0)
STOP = Twist(0.0, 0.0, 0.0)
STATUS_PERIOD_S = 1.0
MOTORS_FIRST_RETRY_S = 0.2
UNKNOWN_SPEEDS = (math.nan, math.nan, math.nan, math.nan)

# What the world can do to a running daemon: a device, a socket or pigpiod gone, a command refused. Logged in one line;
# anything else is a bug, logged with its traceback.
OPERATIONAL_ERRORS: tuple[type[BaseException], ...] = (OSError, PigpioCommandError, ProtocolError, pigpio.error)
SHUTDOWN_SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP, signal.SIGQUIT)


class _Shutdown(Exception):  # noqa: N818 - a signal, not an error
    """Raised inside the TaskGroup to end it after one of SHUTDOWN_SIGNALS."""


@dataclass(slots=True)
class _Liveness:
    """When each vital loop last made progress (monotonic seconds)."""

    control: float = -math.inf
    filter: float = -math.inf


@dataclass(slots=True)
class _Teleop:
    """The latest valid command and when it arrived."""

    twist: Twist | None = None
    received_at: float | None = None
    stepped_at: float = -math.inf  # when a command last stepped the controller at once


MotorsFactory = Callable[[], MotorOutputs]


class Daemon:
    """robotd's process: wires drivers, estimator, control, teleop and pose socket into one TaskGroup."""

    def __init__(
        self,
        config: RobotdConfig,
        *,
        record: TextIO | None = None,
        clock: Callable[[], float] = time.monotonic,
        encoders: EncoderSource | None = None,
        motors_factory: MotorsFactory | None = None,
        deadman_factory: DeadmanFactory | None = None,
        hardware: Hardware | None = None,
        record_mcap: Path | None = None,
    ) -> None:
        self.config = config
        self.clock = clock
        robot = config.robot
        self.geometry = Geometry(robot.wheel_radius_m, robot.lx_m, robot.ly_m)
        saved = calibration_store.load(config.ekf.calibration_file)
        self.estimator = Estimator(
            config.ekf,
            self.geometry,
            robot.ips_offset_m,
            config.encoders.counts_per_rev,
            default_latency_s=config.marvelmind.default_latency_s,
            calibration=None if saved is None else saved.calibration,
            noise=None if saved is None else saved.noise,
        )
        self._calibration_keeper = calibration_store.CalibrationKeeper(config.ekf.calibration_file)
        self.controller = MotionController(
            self.geometry,
            config.control,
            config.teleop,
            duty_limit=config.motors.duty_limit,
            on_fault=self._on_stall_fault,
        )
        # the wheels of the configured back-end (robotd.daemon.hardware); a test may inject its own parts
        wheels = hardware or build_hardware(config, clock)
        self.encoders = encoders if encoders is not None else wheels.encoders
        self._motors_factory = motors_factory or wheels.motors_factory
        self.motors: MotorOutputs | None = None
        self.pacer = ControlPacer(self.controller.period_s, config.teleop.deadman_timeout_s)
        # the back-end's deadman guards the real motors; injected motors (tests) get the deadman injected with them.
        # Its heartbeat at the pace of the loop at rest, driving or not: a few per timeout is all it needs
        self.deadman = DeadmanKeeper(
            deadman_factory or (wheels.deadman_factory if motors_factory is None else None),
            on_trip=self._on_deadman_trip,
            on_lost=self._on_deadman_lost,
            uninstall_timeout_s=config.pigpiod.connect_timeout_s,
            heartbeat_s=self.pacer.rest_period_s,
            clock=clock,
        )
        self._shutdown_signal = "?"
        self.marvelmind = MarvelmindReader(config.marvelmind, self._on_marvelmind, clock)
        self.teleop_receiver = receiver_from_config(config.teleop)
        self.notifier = Notifier()
        pose_socket = config.pose_socket
        self.status_period_s = 1.0 / pose_socket.status_rate_hz
        self.pose_server = posesock.PoseServer(
            pose_socket.path,
            int(pose_socket.mode, 8),
            hello=posesock.hello_message(pose_socket.rate_hz, pose_socket.status_rate_hz),
            queue_size=pose_socket.client_queue,
            stall_s=pose_socket.client_stall_s,
            max_clients=pose_socket.max_clients,
        )
        self.control_periods = PeriodStats()
        self._last_fix_arrival: float | None = None
        self._teleop = _Teleop()
        self._teleop_socket: TeleopSocket | None = None
        self._alive = _Liveness()
        self._wheel_speeds: tuple[float, float, float, float] = ZERO
        self._odometry_state = "waiting"
        self._motors_ready_after = -math.inf
        self._motors_lost = asyncio.Event()
        self._counters: dict[str, int] = {
            "control_steps": 0, "motor_failures": 0, "teleop_commands": 0, "stall_faults": 0,
        }  # fmt: skip
        self._recorder: live.EventSink | None = self._open_recorder(record)
        # the live view and the MCAP recording (robotd.viz): every sensor log event reaches it through the recorder
        self.viewer = live.viewer_for(config, self.geometry, record_mcap, clock)
        if self.viewer is not None:
            self._recorder = live.Tee(self._recorder, self.viewer, daemon_meta(config))
        self.fleet = fleet_link(config.fleet, self._fleet_status, self._on_fleet_hold)  # None when off

    # --- producers' callbacks (on the loop) -----------------------------------------------------------------

    def _on_ticks(self, ticks: WheelTicks) -> None:
        self.estimator.on_wheels(ticks.t, ticks.ticks)
        # while the encoder stream is lost the speeds read 0 without meaning it: unknown (NaN) makes the PID drive
        # open-loop rather than wind up against wheels it cannot see, and keeps the stall guard from blaming them
        lost = ticks.degraded and not any(ticks.speeds_rad_s)
        self._wheel_speeds = UNKNOWN_SPEEDS if lost else ticks.speeds_rad_s
        self._odometry_state = "degraded" if ticks.degraded else "ok"
        self._alive.filter = self.clock()
        if self._recorder is not None:
            self._recorder.write(sensorlog.Wheels(ticks.t, ticks.ticks))

    def _on_marvelmind(self, event: MarvelmindEvent) -> None:
        if isinstance(event, Position):
            # a time-shift of 0 means the beacon did not say: the estimator learns the delay (NaN: no measurement time)
            t_meas = math.nan if event.time_shift_s == 0.0 else event.t_meas
            diagnostics = self.estimator.on_fix(event.arrival, event.x, event.y, t_meas)
            self._last_fix_arrival = event.arrival
            if self.viewer is not None:
                self.viewer.fix(event.arrival, event.x, event.y, diagnostics)
            if self._recorder is not None:
                self._recorder.write(sensorlog.IpsFix(event.arrival, event.x, event.y, event.z, t_meas))
            self._publish_pose()  # a fix reaches the pose socket now, not at the next period
            # what the filter learns from the fix (a calibration window's fit takes milliseconds) waits for the next
            # input, which settles it first (Estimator.settle): not on the fix's way to the pose socket, nor in the
            # way of the pose's readers, and no wake-up of its own
        elif isinstance(event, FixUnavailable):
            self.estimator.on_fix_lost(event.arrival)
            if self._recorder is not None:
                self._recorder.write(sensorlog.IpsLost(event.arrival))
        elif isinstance(event, StationaryBeacons) and self.viewer is not None:
            self.viewer.beacons(event)

    def _on_teleop(self, message: TeleopMessage) -> None:
        teleop = self._teleop
        # An explicit stop brakes at the acceleration limit, then the controller turns the motors off (IDLE):
        # cutting the duties at speed would let the robot coast an unknown distance.
        twist = STOP if isinstance(message, StopCommand) else message.twist
        teleop.twist, teleop.received_at = twist, message.received_at
        self._counters["teleop_commands"] += 1
        if self._recorder is not None:
            self._recorder.write(sensorlog.Command(message.received_at, twist.vx, twist.vy, twist.wz))
        self.pacer.command_arrived()  # a loop at rest steps at once and resumes its period
        socket = self._teleop_socket
        if socket is not None and not socket.watching:
            return  # the wheels are driven: the loop read this command itself, and steps with it now
        # The wheels are not driven (the loop watches the socket): the command reaches the motors now, not at the
        # next period; but at most one command per half period does, so a flood of valid commands cannot run the
        # controller and the motor writes at its rate: the control loop applies a command that arrives sooner at
        # its next tick.
        now = self.clock()
        if now - teleop.stepped_at >= 0.5 * self.controller.period_s:
            teleop.stepped_at = now
            self._control_step(now)

    # --- tasks --------------------------------------------------------------------------------------------------

    async def run(self) -> int:
        """Run until a shutdown signal (returns 0) or a failure (returns 1); the motors are zeroed on every way out."""
        loop = asyncio.get_running_loop()
        stop = asyncio.Event()
        for signum in SHUTDOWN_SIGNALS:
            loop.add_signal_handler(signum, self._on_shutdown_signal, stop, signum)
        status = 1
        transport: TeleopSocket | None = None
        if self._recorder is not None:
            self._recorder.start()
        try:
            await self._connect_motors()
            Path(self.config.pose_socket.path).parent.mkdir(parents=True, exist_ok=True)
            await self.pose_server.start()
            transport = await open_teleop(self.config.teleop, self.teleop_receiver, self._on_teleop)
            self._teleop_socket = transport
            # Everything built so far (modules, gpiozero, numpy, the drivers) lives as long as the process: out of
            # the cyclic collector's sight, its passes stay short and cannot stall a control period.
            gc.collect()
            gc.freeze()
            async with asyncio.TaskGroup() as tasks:
                tasks.create_task(self.encoders.run(self._on_ticks), name="encoders")
                tasks.create_task(self.marvelmind.run(), name="marvelmind")
                tasks.create_task(self._control_loop(), name="control")
                tasks.create_task(self._pose_loop(), name="pose")
                tasks.create_task(self._health_loop(), name="health")
                tasks.create_task(self._motor_supervisor(), name="motors")
                tasks.create_task(self.deadman.follow(), name="deadman")
                tasks.create_task(self._until(stop), name="signals")
                if self.fleet is not None:
                    tasks.create_task(self.fleet.run(), name="fleet")
                self.notifier.ready(status="running")
                log.info("robotd running: teleop udp %s:%d, pose socket %s", self.config.teleop.bind,
                         self.config.teleop.port, self.config.pose_socket.path)  # fmt: skip
        except* _Shutdown:
            status = 0
        except* Exception as group:  # noqa: BLE001 - any failure ends the daemon; _log_failures says which, how
            self._log_failures(group)
        finally:
            self._zero_motors()  # first, whatever happened
            await self.deadman.uninstall()
            try:
                self.estimator.settle()  # what the last fix taught, before it is saved
            except Exception:
                log.exception("learning from the last fix failed")
            self._calibration_keeper.maybe_save(
                self.estimator.calibration, self.clock(), force=True, noise=self.estimator.learnt_noise
            )
            self.notifier.stopping("stopping")
            for signum in SHUTDOWN_SIGNALS:
                loop.remove_signal_handler(signum)
            if transport is not None:
                self._teleop_socket = None
                transport.close()
            await self.pose_server.close()
            self._close_motors()
            if self._recorder is not None:
                self._recorder.close()
            self.notifier.close()
        return status

    @staticmethod
    def _log_failures(group: BaseExceptionGroup[Exception]) -> None:
        """One line for each operational failure; a bug's traceback at ERROR, where journald keeps it."""
        for error in _leaves(group):
            if isinstance(error, OPERATIONAL_ERRORS):
                log.error("robotd stopping after a failure: %s: %s", type(error).__name__, error)
            else:
                log.error(
                    "robotd stopping after an unexpected error: %s: %s", type(error).__name__, error, exc_info=error
                )

    def _on_shutdown_signal(self, stop: asyncio.Event, signum: int) -> None:
        self._shutdown_signal = signal.Signals(signum).name
        stop.set()

    async def _until(self, stop: asyncio.Event) -> None:
        await stop.wait()
        log.info("robotd stopping on signal %s", self._shutdown_signal)
        raise _Shutdown

    async def _control_loop(self) -> None:
        """Step the controller at its rate, or at rest only for the deadman's heartbeat (robotd.daemon.pacer). While
        the wheels are driven it reads the teleop socket itself at every period; while they are not, the socket is
        watched and a command steps the controller at once, from `_on_teleop` (robotd.daemon.teleop_socket)."""
        while True:
            teleop = self._teleop_socket
            if teleop is not None and not teleop.watching:
                teleop.poll()  # the commands that arrived since the last period
            now = self.clock()
            self._control_step(now)
            if self.viewer is not None:
                self.viewer.control(now, self.controller.last, self._wheel_speeds)
            self.deadman.bump()  # from here, not from a task of its own: a loop that stops stepping stops bumping
            at_rest = self._at_rest(now)
            if at_rest:
                self.control_periods.pause()  # a parked robot's heartbeat is not a control period
            else:
                self.control_periods.tick(now)
            if teleop is not None:
                teleop.watch(at_rest or not any(self.controller.last.duties))
            await self.pacer.next_step(at_rest=at_rest)

    def _at_rest(self, now: float) -> bool:
        """Motors off and no command for the deadman timeout: nothing changes until a command arrives."""
        received = self._teleop.received_at
        if received is not None and now - received <= self.config.teleop.deadman_timeout_s:
            return False
        return self.controller.last.state is not ControlState.DRIVING

    def _control_step(self, now: float) -> None:
        teleop = self._teleop
        fresh = teleop.received_at is not None and teleop.received_at > self._motors_ready_after
        fresh = fresh and (self.fleet is None or not self.fleet.held)  # a fleet stop holds the motors off
        command = teleop.twist if fresh else None
        duties = self.controller.step(now, command, teleop.received_at if fresh else None, self._wheel_speeds)
        self._counters["control_steps"] += 1
        self._alive.control = now
        if self.motors is None:
            return
        try:
            self.motors.set_duties(duties)
        except Exception as error:  # noqa: BLE001 - pigpiod gone: zero what we can, reconnect, say so once
            self._counters["motor_failures"] += 1
            log.warning("motor outputs failed (%s): reconnecting to pigpiod", error)
            self._close_motors()
            self._motors_lost.set()

    async def _connect_motors(self) -> None:
        motors = await asyncio.to_thread(self._motors_factory)
        motors.zero()
        try:
            await self.deadman.install()
        except BaseException:
            with contextlib.suppress(Exception):
                motors.close()  # motors no deadman guards are not kept
            raise
        # published only now, with no await before the caller's next step: no command drives them before that
        self.motors = motors

    async def _motor_supervisor(self) -> None:
        """Re-connect the motor outputs whenever they are lost."""
        while True:
            await self._motors_lost.wait()
            self._motors_lost.clear()
            await self._reconnect_motors()

    async def _reconnect_motors(self) -> None:
        backoff = Backoff(MOTORS_FIRST_RETRY_S, self.config.pigpiod.reconnect_max_s)
        while self.motors is None:
            await asyncio.sleep(backoff.next_delay())
            try:
                await self._connect_motors()
            except Exception as error:  # noqa: BLE001 - keep trying with backoff until pigpiod is back
                log.debug("pigpiod still unavailable: %s", error)
                continue
            # only a command that arrives from now on drives the motors again
            self._motors_ready_after = self.clock()
            log.info("motor outputs reconnected; waiting for a fresh command")

    def _zero_motors(self) -> None:
        if self.motors is not None:
            try:
                self.motors.zero()
            except Exception as error:  # noqa: BLE001 - nothing more can be done here than to say so
                log.error("could not zero the motors: %s", error)

    def _close_motors(self) -> None:
        self.deadman.drop()
        motors, self.motors = self.motors, None
        if motors is not None:
            with contextlib.suppress(Exception):
                motors.close()

    # --- the deadman in pigpiod -----------------------------------------------------------------------------------

    def _on_deadman_lost(self, error: OSError) -> None:
        self._counters["motor_failures"] += 1
        log.warning("pigpiod deadman lost (%s): reconnecting to pigpiod", error)
        self._close_motors()
        self._motors_lost.set()

    def _on_deadman_trip(self, trips: int) -> None:
        log.warning(
            "the deadman stopped the motors (robotd was stalled; %d time(s) so far): waiting for a fresh "
            "command", trips
        )  # fmt: skip
        self._zero_motors()  # the pins were written behind the motor outputs' back: write them all again
        self._motors_ready_after = self.clock()

    async def _pose_loop(self) -> None:
        period = 1.0 / self.config.pose_socket.rate_hz
        next_status = self.clock()
        loop = asyncio.get_running_loop()
        while True:
            if not self._pose_subscribers_besides_clients:
                await self.pose_server.wait_for_clients()  # nobody listening: nothing to wake for
            # on the shared grid: at 20 Hz every other wake-up is the control loop's at 50 Hz
            await sleep_until(next_tick(loop.time(), period))
            self._publish_pose()
            now = self.clock()
            if now >= next_status:
                next_status = now + self.status_period_s
                status = self._status_message(now)
                self.pose_server.publish(status)
                if self.viewer is not None:
                    self.viewer.status(status)

    @property
    def _pose_subscribers_besides_clients(self) -> bool:
        """The fleet link or the live view takes every pose, pose-socket clients or not."""
        return self.fleet is not None or self.viewer is not None

    def _publish_pose(self) -> None:
        if not self.pose_server.clients and not self._pose_subscribers_besides_clients:
            return  # the filter's estimate at a fix is for readers: without one, it is not worth building
        now = self.clock()
        estimate = self.estimator.pose(now)
        health = self.marvelmind.health(now)
        fix_state = "stale" if health.stale else estimate.state.value
        message = posesock.pose_message(
            t=estimate.t,
            stamp=time.time(),
            pose=(estimate.x, estimate.y, estimate.theta),
            twist=(estimate.vx, estimate.vy, estimate.wz),
            covariance=estimate.cov,
            fix_age_s=estimate.fix_age_s if math.isfinite(estimate.fix_age_s) else None,
            fix_state=fix_state,
            odometry_state=self._odometry_state,
        )
        # robotd's addition to the pose: when the newest fix given to the filter arrived (monotonic s), so a reader
        # can tell which fix a pose contains (and measure the fix-to-pose latency)
        message["fix_arrival_t"] = self._last_fix_arrival
        self.pose_server.publish(message)
        if self.viewer is not None:
            self.viewer.pose(message)
        if self.fleet is not None:
            self.fleet.latest_pose = message

    def _status_message(self, now: float) -> dict[str, Any]:
        encoders = self.encoders.counters
        health = self.marvelmind.health(now)
        drivers: dict[str, dict[str, Any]] = {
            "encoders": {
                "reports": encoders.reports,
                "lost_reports": encoders.lost_reports,
                "illegal_transitions": list(encoders.illegal_transitions),
                "reconnects": encoders.reconnects,
                "state": self._odometry_state,
            },
            "marvelmind": {
                **self.marvelmind.counters.as_dict(),
                "state": health.state.value,
                "connected": health.connected,
                "stale": health.stale,
            },
            "teleop": dict(self.teleop_receiver.counters()),
            "control": {
                **self._counters,
                "state": self.controller.last.state.value,
                "period": self.control_periods.summary(),
                "faults": self._control_faults(),
            },
            "pose_socket": dict(self.pose_server.counters),
        }
        if self._recorder is not None:
            drivers["recorder"] = self._recorder.counters()
        if self.viewer is not None:
            drivers["viewer"] = self.viewer.counters()
        if self.fleet is not None:
            drivers["fleet"] = self.fleet.counters()
        estimator = self.estimator
        diagnostics = {
            **estimator.counters,
            "calibration": estimator.calibration.as_dict(),
            "process_noise_scale": round(estimator.process_noise_scale, 4),
            "heading_noise_scale": round(estimator.heading_noise_scale, 4),
            "ips_sigma_m": round(math.sqrt(estimator.learnt_noise.ips_var), 5),
        }
        return posesock.status_message(t=now, stamp=time.time(), drivers=drivers, filter_diagnostics=diagnostics)

    async def _health_loop(self) -> None:
        """Ping the watchdog while the control loop and the filter make progress; say how things stand."""
        period = self.notifier.watchdog_period_s or STATUS_PERIOD_S
        control_limit = 5.0 * self.controller.period_s
        filter_limit = 5.0 / self.config.encoders.publish_rate_hz + 1.0
        while True:
            await asyncio.sleep(period)
            now = self.clock()
            control_ok = now - self._alive.control < control_limit + period
            filter_ok = now - self._alive.filter < filter_limit + period
            if control_ok and filter_ok:
                self.notifier.watchdog()
            # here, not with the status: the status is built only for readers, the calibration is kept regardless
            self._calibration_keeper.maybe_save(self.estimator.calibration, now, noise=self.estimator.learnt_noise)
            estimate = self.estimator.pose(now)
            health = self.marvelmind.health(now)
            self.notifier.status(
                f"pose ({estimate.x:.2f}, {estimate.y:.2f}, {math.degrees(estimate.theta):.0f} deg) "
                f"fix {('stale' if health.stale else estimate.state.value)}, odometry {self._odometry_state}, "
                f"control {self.controller.last.state.value}, {self.pose_server.clients} pose clients"
            )

    def _on_stall_fault(self, fault: StallFault | None) -> None:
        """The controller latched a stall fault (motors off) or cleared it on a fresh command: say so once."""
        if fault is None:
            log.info("control: stall fault cleared by a fresh command; driving again")
            return
        self._counters["stall_faults"] += 1
        log.warning(
            "control: %s driven hard but not turning for %.2f s (dead encoder or blocked wheel?): all motors stopped"
            " until a fresh command (let go, then command again)",
            ", ".join(fault.wheels), self.config.control.stall_timeout_s,
        )  # fmt: skip

    def _control_faults(self) -> list[dict[str, Any]]:
        """The faults holding the motors off, for the status message."""
        fault = self.controller.fault
        if fault is None:
            return []
        return [{"kind": "stall", "wheels": list(fault.wheels), "since": fault.since}]

    def _on_fleet_hold(self, held: bool) -> None:
        """A fleet stop (held) cuts the motors in this call; after its release only a fresh command drives."""
        now = self.clock()
        self._motors_ready_after = now
        log.warning("fleet stop %s", "in force: motors off until released" if held else "released: awaiting a command")
        self._control_step(now)

    def _fleet_status(self) -> dict[str, Any]:
        """The status message, with the heading's calibration, for the fleet's retained status."""
        now = self.clock()
        calibration = {"heading": self.estimator.modes.heading.value, "position": self.estimator.modes.position.value}
        return self._status_message(now) | {"calibration": calibration}

    def _open_recorder(self, stream: TextIO | None) -> Recorder | None:
        return None if stream is None else Recorder(stream, daemon_meta(self.config))


def _leaves(group: BaseExceptionGroup[Exception]) -> list[Exception]:
    """The exceptions of a group, nested groups flattened."""
    leaves: list[Exception] = []
    for error in group.exceptions:
        if isinstance(error, BaseExceptionGroup):
            leaves += _leaves(error)
        else:
            leaves.append(error)
    return leaves


def run_daemon(config: RobotdConfig, record_path: Path | None = None, record_mcap: Path | None = None) -> int:
    """Run the daemon in a fresh event loop; returns the process exit status.

    `record_path` names the sensor log to create, `record_mcap` the MCAP recording (never an existing file: see
    `robotd.daemon.recorder.create_log`, which raises RecordingError when it cannot).
    """
    if record_mcap is not None:
        stream, created_mcap = create_log(record_mcap)
        stream.close()  # the name is ours now; the SDK's MCAP writer opens it again, in binary
        log.info(
            "recording MCAP to %s%s",
            created_mcap,
            "" if created_mcap == record_mcap else f": {record_mcap} exists and is kept",
        )
        record_mcap = created_mcap
    if record_path is None:
        return asyncio.run(Daemon(config, record_mcap=record_mcap).run())
    record, created = create_log(record_path)
    if created != record_path:
        log.info("recording to %s: %s exists and is kept", created, record_path)
    else:
        log.info("recording to %s", created)
    return asyncio.run(Daemon(config, record=record, record_mcap=record_mcap).run())
