"""Offline evaluation: replay of sensor logs, experiments over seeds, metrics, estimates files, reports and plots.

Public API: `replay` (replay, write_outputs, format_table), `experiment`, `metrics` (score, Trajectory), `plots`.
"""
