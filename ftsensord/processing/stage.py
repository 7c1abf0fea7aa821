"""What every stage of a sensor's pipeline has in common.

A stage owns one physical effect the calibration did not see: a warm sensor
(`temperature`), a motor's gradient fixed in the world (`stray`), the silicone's creep
(`creep`). `pipeline.SensorPipeline.step` applies each at its place, the flux before the
estimator or the wrench after it (their inputs differ by physics); the rest of a stage's
life goes through this one shape, so that the loop, the tare, control and status handle
every stage alike and know none by name.

Adding a stage: a module with a class of this shape, a field of `SensorPipeline` built in
its `build`, the line in `step` that applies it, and the class in `pipeline.STAGE_TYPES`.
"""

from __future__ import annotations

from typing import Any, ClassVar, Protocol

import numpy as np


class Stage(Protocol):
    #: Its key in a sensor's part of the `status` reply (None there when the stage is off).
    name: ClassVar[str]

    def configure(self, rate_hz: float) -> None:
        """The loop runs at ``rate_hz`` (Hz) from now on."""

    def gap(self, periods: int) -> None:
        """``periods`` cycles made no sample (skipped deadlines); negative: the loop's time
        went back (a clock step), so nothing of the past is known to be before now."""

    def restart(self) -> None:
        """The estimate's history broke (another estimator): what was learnt from it goes."""

    def tared(self, zero: np.ndarray) -> np.ndarray:
        """The pipeline takes ``zero`` (T, the mean no-load flux as this stage sees it) as its
        new zero; returns it as the stages after this one and the estimator see it."""

    def status(self) -> dict[str, Any] | None:
        """Its part of the sensor's `status` (None: calibrated with nothing to do)."""
