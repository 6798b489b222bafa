"""The process systemd runs: one TaskGroup wiring drivers, estimator, control, teleop, pose socket and recorder.

Public API: `service` (Daemon, run_daemon), `control` (MotionController), `teleop` (the wire format, TeleopReceiver,
TeleopSender), `posesock` (PoseServer), `preflight`, `recorder`.
"""
