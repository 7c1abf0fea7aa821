"""Shared fixtures: a noiseless simulated bus on a virtual clock."""

from __future__ import annotations

import numpy as np
import pytest

from ftsensord import mlx90393 as mlx
from ftsensord.driver import MLX90393
from ftsensord.sim import NOISELESS, SimulatedBus, StaticScene, VirtualClock, simulated_bus

ADDR = 0x0C


@pytest.fixture
def scene() -> StaticScene:
    """Two chips with distinct fields (T, chip frame)."""
    return StaticScene({0x0C: np.array([100e-6, -200e-6, 1500e-6]),
                        0x14: np.array([-50e-6, 25e-6, -800e-6])}, {0x0C: 31.5})


@pytest.fixture
def bus(scene: StaticScene) -> SimulatedBus:
    return simulated_bus(scene, clock=VirtualClock(), noise=NOISELESS)


@pytest.fixture
def chip(bus: SimulatedBus) -> MLX90393:
    """A driver for 0x0C, reset and configured with the paper's settings."""
    drv = MLX90393(bus, ADDR, sleep=bus.sleep)
    drv.reset()
    drv.configure(mlx.Settings())
    return drv
