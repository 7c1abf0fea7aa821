"""ftsensord: a daemon for a soft, low-cost 6-axis magnetic force/torque sensor.

The package is a house of floors that follow the data's way up; a module
imports only from its own floor or those below (tests/test_layout.py checks it):

1. `errors`, `docfile`: the exception root; reading TOML and JSON with errors
   that name the file, the key and what was expected.
2. `model`: pure maths and physics (SE(3), registration, magnet fields, the
   sensor's geometry, the linear and nonlinear estimators).
3. `chip`: the MLX90393's facts and driver, and the I2C wire's.
4. `sim`: the fake bus (emulated chips, scenes, physics, faults, clocks).
5. `acquire`: choosing a bus by one string, the schedulers, the cycle bound,
   chip health and recovery, scanning.
6. `calibration`: datasets, the rig, the linear and nonlinear fits, the
   calibration file, the report.
7. `stages`: what acts on a sensor's flux before its estimator and on its
   wrench after (the temperature's laws), apart from the service's loop.
8. `service`: configuration, the loop, the per-sensor pipeline, tare, control,
   status, the wire format, sockets, sd_notify.
9. `client`: subscribing to the streams, sending control requests.
10. `recording`, `plot`, `bridge`, `echo`: streams to CSV, NPZ or MCAP files; live
    plots; live viewers; printed lines.
11. `cli`: the `ftsensord` command.

The names below are the public face; they are imported on first use, so
``import ftsensord`` stays cheap and pulls in no floor it does not need.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

_EXPORTS = {
    "open_bus": "ftsensord.acquire.bus",
    "MLX90393": "ftsensord.chip.driver",
    "load_config": "ftsensord.service.config",
    "Subscriber": "ftsensord.client",
    "ControlClient": "ftsensord.client",
    "FtsensordError": "ftsensord.errors",
}
__all__ = ["ControlClient", "FtsensordError", "MLX90393", "Subscriber", "__version__", "load_config", "open_bus"]

if TYPE_CHECKING:
    from .acquire.bus import open_bus
    from .chip.driver import MLX90393
    from .client import ControlClient, Subscriber
    from .errors import FtsensordError
    from .service.config import load_config


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'ftsensord' has no attribute {name!r}")
