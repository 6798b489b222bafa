"""Stand-ins that speak the real protocols: a virtual pigpiod (pins, notifications, scripts) and a virtual Marvelmind.

Public API: `pigpiod.VirtualPigpiod`, `marvelmind` (a pseudo-terminal streaming real frames, HedgehogPacket),
`quadrature_signal`, `l298` (the bridge rule checked on a pin history); for the Raspberry Pi 5 back-end, `event_pipe`
(kernel edge-event records on a pipe), `pwm_sysfs` (a directory laid out as /sys/class/pwm) and `output_lines`. Each
says in its docstring what it does not model.
"""
