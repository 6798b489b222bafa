"""The simulated world: motors and physics, the floor, the IPS error model, scenarios, offline and live runners.

Public API: `offline` (simulate, run), `live` (the virtual robot in real time: `robotd vhw`), `scenarios`.
"""
