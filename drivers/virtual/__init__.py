"""Stand-ins that speak the real protocols: a virtual pigpiod (pins, notifications, scripts) and a virtual Marvelmind.

Public API: `pigpiod.VirtualPigpiod`, `marvelmind` (a pseudo-terminal streaming real frames, HedgehogPacket),
`quadrature_signal`, `l298` (the bridge rule checked on a pin history). Each says in its docstring what it does not
model.
"""
