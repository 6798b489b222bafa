"""pigpiod: its socket protocol (sans-I/O), the asyncio client, the notification stream and the deadman script.

Public API: `protocol` (Cmd, CommandDecoder, REPORT_DTYPE), `client` (PigpioLink, PigpiodUnavailableError, probe,
stop_pigpio_client for the `pigpio` library's clients), `notifications`, `deadman` (PigpioDeadman, find_deadmen).
"""
