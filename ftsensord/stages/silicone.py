"""The silicone's memory undone: a per-axis recursive inverse of its creep (`model.viscoelastic`),
from the series the calibration identified (`calibration.creep`), on the estimated wrench
behind either estimator, before the overload check and the smoothing filter.

Its state spans seconds to minutes of samples, so what enters it must be clean: a sample
flagged as off the sensor's model (a chip missing, stale, saturated or left out, an invalid
or fallen-back estimate) passes through as it is, flagged, and the state is dropped; the next
clean sample starts afresh, taken as a load long held. A tare, an estimator switch and a
rate change start afresh too (the period is part of the filter).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..calibration.creep import SiliconeCalibration
from ..model.viscoelastic import CreepInverse


class CreepCompensation:
    """One sensor's inverse at ``rate_hz``; ``restarts`` counts the times it started afresh
    (tares, rate changes and flagged samples)."""

    def __init__(self, calibration: SiliconeCalibration, rate_hz: float):
        self.calibration = calibration
        self.restarts = 0
        self.configure(rate_hz)

    def configure(self, rate_hz: float) -> None:
        """A new loop rate: the filter's coefficients for its period, its state dropped."""
        self.rate_hz = rate_hz
        self.inverse = CreepInverse(self.calibration.relaxation, 1.0 / rate_hz, self.calibration.scale)

    def reset(self) -> None:
        self.inverse.reset()
        self.restarts += 1

    def apply(self, wrench: np.ndarray, clean: bool) -> np.ndarray:
        """The load (N, Nm) behind this sample's estimated ``wrench``; ``clean``: nothing
        flagged that puts the sample off the sensor's model (the caller's flags decide)."""
        if not clean or not np.all(np.isfinite(wrench)):
            if self.inverse.last is not None:
                self.reset()
            return wrench
        return self.inverse.apply(wrench)

    def status(self) -> dict[str, Any]:
        return {"relaxation": self.calibration.relaxation.pairs(), "scale": round(self.calibration.scale, 5),
                "rate_hz": self.rate_hz, "restarts": self.restarts}
