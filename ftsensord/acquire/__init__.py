"""Floor 5, acquisition: getting every chip's reading once a cycle, on any bus.

Owns choosing a bus by one string (`bus.open_bus`), the three schedulers
(`reader.Reader`) and the cycle's results they return (`readings.Readings`: the usual
cycle as one array), how fast each can go (`bound.cycle_bound`), chip health and
recovery (`health.ChipCare`), and probing a bus (`scan`).

May import: `chip`, `errors`, and `sim` (only to open a simulated bus when the
string asks for one). Not calibration or service.
"""
