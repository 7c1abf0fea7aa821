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
7. `protocol`: what the daemon and every client share: the wire format, the
   orientation stream, endpoints, the runtime folder.
8. `config`: the configuration file, read and validated (nothing started).
9. `processing`: one sensor's way from chip results to a flagged, filtered
   wrench: the pipeline, the redundancy check, the stages (temperature, stray
   field, creep), filters, tare, gravity.
10. `daemon`: the loop, control, status, reloads, `ftsensord run`, and the OS
    plumbing (sd_notify, real time, connections, the runtime folder).
11. `client`: subscribing to the streams, sending control requests.
12. `recording`, `plot`, `foxglove`, `ros2`, `echo`: streams to CSV, NPZ or MCAP
    files; live plots; live viewers; the ROS 2 graph; printed lines.
13. `cli`: the `ftsensord` command.
14. `testing`: the daemon harness the tests and benchmarks use (as gpiozero ships
    its mock pin factory); nothing in the package imports it.

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
    "load_config": "ftsensord.config.file",
    "Subscriber": "ftsensord.client",
    "ControlClient": "ftsensord.client",
    "FtsensordError": "ftsensord.errors",
}
__all__ = [
    "ControlClient",
    "FtsensordError",
    "MLX90393",
    "Subscriber",
    "__version__",
    "load_config",
    "open_bus",
]

if TYPE_CHECKING:
    from ftsensord.acquire.bus import open_bus
    from ftsensord.chip.driver import MLX90393
    from ftsensord.client import ControlClient, Subscriber
    from ftsensord.config.file import load_config
    from ftsensord.errors import FtsensordError


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'ftsensord' has no attribute {name!r}")
