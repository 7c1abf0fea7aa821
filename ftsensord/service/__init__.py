"""Floor 8, the service: the daemon that turns cycles of flux into published wrenches.

Owns the configuration (`config`; its sensor tables `sensorconf`, endpoints and their
security `endpoints`, file and runtime-folder paths `paths`), the loop's timing (`loop`), the per-sensor
pipeline from chip results to a flagged, filtered wrench (`pipeline`,
`filters`), tare (`tare`), control requests (`control`), status (`status`),
the coordinator over them (`daemon`), the published format (`wire`), sockets
and signals (`run`) and systemd's notify protocol (`sdnotify`).

May import every floor below: `model`, `chip`, `sim` (to open a simulated bus
with a real-time clock), `acquire`, `calibration`, `docfile`, `errors`.
"""
