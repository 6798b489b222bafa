"""robotd's configuration: YAML in, frozen dataclasses out, every error by its dotted path.

Public API: `model` (RobotdConfig and its sections, load, parse, paper_preset, config_reference), `schema`
(ConfigError), `yamltext` (the safe loader), `motorpins` (what stop-motors reads from a broken file), `sim` (the sim
section).
"""
