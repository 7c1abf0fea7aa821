"""One sensor's way from a cycle's chip results to a flagged, filtered wrench.

`SensorPipeline` stacks the sensor's flux (T, in chip order), decides which
chips are usable, estimates the wrench (N, Nm, in the sensor's frame) with
the chosen estimator, flags what the sample went through, and smooths it.
A failing chip's data never enter a wrench: a chip without new data gives its
previous reading (flagged stale), a chip that did not answer NaN (flagged
missing), a saturated chip its reading (flagged, not used).
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..acquire.health import ChipResult
from ..errors import ChipRefusedError
from ..model.linear import SENSOR_RANGE, LinearModel
from ..model.nonlinear import NonlinearEstimator
from . import wire
from .config import SensorConfig
from .filters import WrenchFilter
from .loop import STATS_WINDOW

#: A linear estimate is flagged `extrapolated` past this multiple of the calibration's
#: largest load on an axis: up to 1.5x no axis's error relative to the load has grown
#: 1.5-fold, by 3x one has nearly tripled (benchmarks/extrapolation.py, docs/calibration.md).
EXTRAPOLATION_MARGIN = 1.5


@dataclass
class SensorSample:
    """What one cycle made of one sensor: its flux (T) and wrench (N, Nm), each with its flags."""

    flux: np.ndarray
    flux_flags: int
    wrench: np.ndarray  # after the filter
    flags: int
    valid: bool  # an estimate was possible (the wrench is not NaN)


@dataclass
class SensorPipeline:
    config: SensorConfig
    model: LinearModel
    filter: WrenchFilter
    max_missing_chips: int
    last_flux: np.ndarray
    tared: bool = False
    estimator: str = "linear"
    nonlinear: NonlinearEstimator | None = None  # built from the calibration when it has one
    zero_twist: np.ndarray | None = None  # the nonlinear estimator's no-load deflection
    tare_wrench: np.ndarray = field(default_factory=lambda: np.zeros(6))  # what the tare removes (N, Nm)
    fallbacks: int = 0
    estimate_s: deque[float] = field(default_factory=lambda: deque(maxlen=STATS_WINDOW))

    @classmethod
    def build(cls, s: SensorConfig, smoothing: WrenchFilter, max_missing_chips: int) -> SensorPipeline:
        nl = s.calibration.nonlinear
        return cls(s, s.calibration.model, smoothing, max_missing_chips, np.full(3 * len(s.addresses), np.nan),
                   estimator=s.estimator, nonlinear=nl.estimator() if nl is not None else None,
                   zero_twist=nl.zero_twist.copy() if nl is not None else None)

    @property
    def name(self) -> str:
        return self.config.name

    def step(self, results: dict[int, ChipResult], base_flags: int = 0) -> SensorSample:
        """This cycle's sample from the chips' ``results`` (by address); ``base_flags``
        apply to every stream of the cycle (e.g. late)."""
        flux, flags, usable = self.flux(results)
        flags |= base_flags
        wrench, wflags = self.estimate(flux, flags, usable)
        valid = not wflags & wire.FLAG_INVALID
        if valid and np.any(np.abs(wrench) > SENSOR_RANGE):
            wflags |= wire.FLAG_OVERLOAD
        return SensorSample(flux, flags, self.filter.update(wrench), wflags, valid)

    def flux(self, results: dict[int, ChipResult]) -> tuple[np.ndarray, int, np.ndarray]:
        """The sensor's stacked flux (T), its flags, and which chips are usable."""
        flux = np.full(3 * len(self.config.addresses), np.nan)
        usable = np.zeros(len(self.config.addresses), dtype=bool)
        flags = 0
        for i, address in enumerate(self.config.addresses):
            r, part = results[address], slice(3 * i, 3 * i + 3)
            m = r.measurement
            if m is not None:
                flux[part] = self.last_flux[part] = m.field_t
                usable[i] = not m.any_saturated
                if m.any_saturated:
                    flags |= wire.FLAG_SATURATED
            elif (isinstance(r.error, ChipRefusedError) and r.error.command == "RM"
                  and np.all(np.isfinite(self.last_flux[part]))):
                flux[part] = self.last_flux[part]
                usable[i] = True
                flags |= wire.FLAG_STALE
            else:
                flags |= wire.FLAG_CHIP_MISSING
        return flux, flags, usable

    def estimate(self, flux: np.ndarray, flags: int, usable: np.ndarray) -> tuple[np.ndarray, int]:
        """The wrench from every chip; from the usable ones (degraded) when one or
        two are missing or saturated; else NaN, flagged invalid."""
        few_missing = (~usable).sum() <= self.max_missing_chips
        if self.estimator == "nonlinear" and self.nonlinear is not None and self.zero_twist is not None:
            if few_missing:
                t0 = time.process_time()
                e = self.nonlinear.estimate(flux, usable)
                self.estimate_s.append(time.process_time() - t0)
                if e.converged:
                    w = self.nonlinear.stiffness @ (e.xi - self.zero_twist)
                    return w, flags | (0 if usable.all() else wire.FLAG_DEGRADED)
            self.fallbacks += 1
            flags |= wire.FLAG_FALLBACK
        if usable.all():
            return self._linear(self.model.wrench(flux), flags)
        if few_missing and self.model.H is not None:
            try:
                return self._linear(self.model.wrench_from(flux, usable), flags | wire.FLAG_DEGRADED)
            except ValueError:
                pass  # the chips left do not see all six axes
        return np.full(6, np.nan), flags | wire.FLAG_INVALID

    def _linear(self, wrench: np.ndarray, flags: int) -> tuple[np.ndarray, int]:
        """A linear estimate, flagged `extrapolated` where the load on the sensor (the
        wrench plus what a tare removed) is beyond the calibration's loads."""
        fitted = self.config.calibration.wrench_range
        if fitted is not None and np.any(np.abs(wrench + self.tare_wrench) > EXTRAPOLATION_MARGIN * fitted):
            flags |= wire.FLAG_EXTRAPOLATED
        return wrench, flags

    def tare(self, zero: np.ndarray) -> np.ndarray:
        """Make ``zero`` (the mean no-load flux, T) the new zero; returns the wrench it removes."""
        self.tare_wrench = self.config.calibration.model.wrench(zero)
        self.model = self.model.with_zero(zero)
        if self.nonlinear is not None:
            e = self.nonlinear.estimate(zero)
            if e.converged:
                self.zero_twist = e.xi
        self.filter.reset()
        self.tared = True
        return self.tare_wrench

    def use(self, estimator: str) -> None:
        """Switch the estimator ("linear" or "nonlinear"); the filter restarts."""
        if estimator == "nonlinear" and self.nonlinear is None:
            raise ValueError(f"no nonlinear calibration for {self.name}")
        self.estimator = estimator
        self.filter.reset()

    def status(self) -> dict[str, Any]:
        return {
            "calibration": str(self.config.calibration_path), "serial": self.config.calibration.serial,
            "frame": self.config.frame, "tared": self.tared, "estimator": self.estimator,
            "nonlinear_calibrated": self.nonlinear is not None, "fallbacks": self.fallbacks,
            "estimate_cpu_us": {"mean": float(np.mean(self.estimate_s)) * 1e6,
                                "max": float(np.max(self.estimate_s)) * 1e6} if self.estimate_s else None,
            "tare_wrench": self.tare_wrench.round(6).tolist(),
        }
