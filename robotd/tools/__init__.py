"""Operator programs: the teleop client, the demo and the supervision of its child processes.

Public API: `teleop_client` (UdpLink), `demo` (run_demo, Children, private_config), `childguard`.
"""
