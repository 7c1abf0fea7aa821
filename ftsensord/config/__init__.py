"""Floor 8, the configuration: one TOML file read and validated, nothing started.

- `file`: the daemon's configuration (`Config`, `load_config`, `reload_config`).
- `sensors`: the ``[[sensor]]`` tables, each validated against its calibration file.
- `frames`: the ``[tool]`` and ``[gravity]`` tables: the tool's frames and weight.
- `ros2conf`: the ``[ros2]`` table.

Every error names the file, the key and what was expected (`docfile`).

May import: `protocol`, `calibration`, `acquire` (bus strings, schedulers, bounds), `chip`,
`model`, `docfile`, `errors`. Never `processing`, `daemon` or the outputs.
"""
