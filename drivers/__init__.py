"""The hardware edge of robotd (encoders, motors, Marvelmind) and its stand-ins (the virtual robot).

Shared by every driver: `drivers.settings` (the plain settings drivers take, as protocols) and
`drivers.backoff.Backoff` (the capped exponential wait of every link that reconnects).
"""
