"""The sensor log format (JSON Lines): typed records, reading with per-line errors, writing, and its hostile-log check.

Public API: `logfile` (read_log, parse_lines, LogWriter, SensorLog and the event records), `logcheck.check`.
"""
