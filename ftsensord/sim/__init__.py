"""Floor 4, the simulator: emulated MLX90393s fed by a scene, behind smbus2's ``i2c_rdwr``.

Owns the emulated chip (`chip`, its conversions in `conversion`), the simulated bus with the kernel's
semantics, wire time and fault hooks (`bus`), clocks (`clock`), the physics
of magnets and stiffness (`physics`), the silicone's memory (`silicone`), loads over time (`loads`), scripted
faults (`faults`) and scene files (`scene`). `simulated_bus` builds a ready
bus from a scene; `ftsensord.acquire.bus.open_bus` calls it for the ``sim``
and ``sim:<scene file>`` specifications.

May import: `chip` (the datasheet's facts), `model` (fields, geometry),
`docfile`, `errors`. Never acquisition, calibration or the service.
"""

from __future__ import annotations

from ftsensord.sim.bus import BusFaults, SimulatedBus, simulated_bus
from ftsensord.sim.chip import NOISELESS, EmulatedMLX90393, FieldSource, NoiseModel
from ftsensord.sim.clock import MonotonicClock, VirtualClock
from ftsensord.sim.faults import Fault, FaultScript
from ftsensord.sim.physics import PhysicalScene, SimSensor, two_sensor_scene
from ftsensord.sim.scene import StaticScene, default_scene, load_scene

__all__ = [
    "Fault",
    "FaultScript",
    "BusFaults",
    "EmulatedMLX90393",
    "FieldSource",
    "MonotonicClock",
    "NOISELESS",
    "NoiseModel",
    "PhysicalScene",
    "SimSensor",
    "SimulatedBus",
    "StaticScene",
    "VirtualClock",
    "default_scene",
    "load_scene",
    "simulated_bus",
    "two_sensor_scene",
]
