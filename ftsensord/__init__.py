"""ftsensord: a daemon for a soft, low-cost 6-axis magnetic force/torque sensor.

Layers, lowest first: `mlx90393` (datasheet facts), `driver` (one chip over a
bus), `bus` (choose a bus by one string), `sim` (the fake bus and its scenes).
"""

__version__ = "0.1.0"
