"""Pure pose estimation: the EKF of the paper made robust; no I/O, no asyncio, nothing of the daemon.

Public API: `estimator.Estimator` (on_wheels, on_twist, on_fix, on_fix_lost, pose), `ekf` (predict, update, wrap_angle),
`modes` (the position and heading state machine).
"""
