"""The silicone's memory undone: a per-axis recursive inverse of its creep (`model.viscoelastic`),
from the series the calibration identified (`calibration.relaxation`), on the estimated wrench
behind either estimator, before the overload check and the smoothing filter.

Its state spans seconds to minutes of samples, so nothing flagged may enter it: a sample
flagged as off the sensor's model (a chip missing, stale, saturated or left out, an invalid
or fallen-back estimate) is compensated from the state without changing it, and the state
coasts through its period on the last clean load, as if held. A fault longer than
`MAX_COAST_S` drops the state: the next clean sample starts afresh, taken as a load long
held. Cycles the loop skipped are coasted through the same way. A tare, an estimator
switch and a rate change start afresh (the zero, the estimate or the period changed).
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from ftsensord.calibration.relaxation import SiliconeCalibration
from ftsensord.model.viscoelastic import CreepInverse

#: The longest run of flagged samples the state coasts through (s): a chip's brief dropout
#: keeps the history (a restart mid-creep costs up to the series' whole fraction of the last
#: load change, 15 % by default, until it has crept); a fault longer than the fast term's
#: second is a load history the state no longer knows.
MAX_COAST_S = 0.5


class CreepCompensation:
    """One sensor's inverse at ``rate_hz``; ``restarts`` counts the times its state was
    dropped (tares, estimator switches, faults and skipped cycles longer than `MAX_COAST_S`).
    Without a ``calibration`` (none identified) it passes every wrench through as it is."""

    name: ClassVar[str] = "silicone"

    def __init__(self, calibration: SiliconeCalibration | None, rate_hz: float):
        self.calibration = calibration
        self.restarts = 0
        self.inverse: CreepInverse | None = None
        self.configure(rate_hz)

    def configure(self, rate_hz: float) -> None:
        """A new loop rate: the filter's coefficients for its period, its state dropped."""
        self.rate_hz = rate_hz
        if self.calibration is not None:
            self.inverse = CreepInverse(self.calibration.relaxation, 1.0 / rate_hz, self.calibration.scale)
        self.max_coast = max(1, round(MAX_COAST_S * rate_hz))
        self.coasted = 0

    def reset(self) -> None:
        if self.inverse is None:
            return
        if self.inverse.last is not None:
            self.restarts += 1
        self.inverse.reset()
        self.coasted = 0

    def restart(self) -> None:
        self.reset()  # the history is of the other estimator's wrenches

    def tared(self, zero: np.ndarray) -> np.ndarray:
        self.reset()  # the zero moved: the history the stage holds is of the old one
        return zero

    def gap(self, periods: int) -> None:
        """``periods`` samples the loop skipped (missed deadlines): the silicone's memory spans
        minutes, so coasted through as flagged samples are, the state dropped once the run
        passes `MAX_COAST_S`; a step back in time drops it at once."""
        if periods < 0:
            self.reset()
        for _ in range(periods):
            if self.inverse is None or self.inverse.last is None:
                return
            self._coast()

    def _coast(self) -> None:
        self.coasted += 1
        if self.coasted > self.max_coast:
            self.reset()
        else:
            self.inverse.coast()  # type: ignore[union-attr]

    def apply(self, wrench: np.ndarray, clean: bool) -> np.ndarray:
        """The load (N, Nm) behind this sample's estimated ``wrench``; ``clean``: nothing
        flagged that puts the sample off the sensor's model (the caller's flags decide)."""
        if self.inverse is None:  # nothing identified: the daemon as without the stage
            return wrench
        finite = bool(np.all(np.isfinite(wrench)))
        if clean and finite:
            self.coasted = 0
            return self.inverse.apply(wrench)
        out = self.inverse.peek(wrench) if finite else wrench
        self._coast()
        return out

    def status(self) -> dict[str, Any] | None:
        if self.calibration is None:
            return None
        return {
            "relaxation": self.calibration.relaxation.pairs(),
            "scale": round(self.calibration.scale, 5),
            "rate_hz": self.rate_hz,
            "restarts": self.restarts,
        }
