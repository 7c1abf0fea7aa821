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

import numpy as np

from .bus import DEFAULT_ADAPTER, DEFAULT_IOCTL_S, BusFaults, SimulatedBus
from .chip import NOISELESS, EmulatedMLX90393, FieldSource, NoiseModel
from .clock import MonotonicClock, VirtualClock
from .faults import Fault, FaultScript
from .physics import PhysicalScene, SimSensor, two_sensor_scene
from .scene import StaticScene, default_scene, load_scene

__all__ = ["Fault", "FaultScript", "BusFaults", "EmulatedMLX90393", "FieldSource", "MonotonicClock", "NOISELESS", "NoiseModel",
           "PhysicalScene", "SimSensor", "SimulatedBus", "StaticScene", "VirtualClock", "default_scene",
           "load_scene", "simulated_bus", "two_sensor_scene"]


def simulated_bus(scene: FieldSource, *, clock: VirtualClock | MonotonicClock | None = None,
                  bus_hz: float | None = None, seed: int | None = 0,
                  noise: NoiseModel = NoiseModel(), adapter: str = DEFAULT_ADAPTER,
                  ioctl_s: float = DEFAULT_IOCTL_S, clock_hz: float | None = None) -> SimulatedBus:
    """A bus with one emulated chip per address of ``scene``, each drifting with its die
    temperature as the scene's part says (`PhysicalScene.chip_drift`; a static scene's do not).

    ``seed`` makes the chips' noise repeatable (None: fresh entropy); each chip
    gets its own stream, so adding a chip does not change another's noise.
    ``adapter``, ``ioctl_s`` (s per ioctl) and ``clock_hz`` (the wire's real
    clock, None: ``bus_hz``) are the board's (`SimulatedBus`); the defaults are
    a Raspberry Pi 4's.
    """
    addresses = scene.addresses
    streams = np.random.SeedSequence(seed).spawn(len(addresses))
    drift = getattr(scene, "chip_drift", None)  # a physical scene's parts drift with heat
    chips = [EmulatedMLX90393(address, scene, rng=np.random.default_rng(stream), noise=noise,
                              drift=None if drift is None else drift(address))
             for address, stream in zip(addresses, streams)]
    faults = getattr(scene, "faults", [])
    return SimulatedBus(chips, clock=clock, bus_hz=bus_hz, script=FaultScript(faults) if faults else None,
                        adapter=adapter, ioctl_s=ioctl_s, clock_hz=clock_hz)
