"""Temperature: what a warm sensor's physics does that its calibration did not see.

The laws (`calibration.thermal.ThermalLaws`: the magnets' remanence and each chip's
sensitivity on the flux, the silicone's stiffness on the wrench) and, when the calibration
measured them, each channel's drift, referred to the calibration's temperature. The flux
is brought to it chip by chip at the chip's own die temperature, before either estimator:
b_ref = b g(T_ref) / g(T_i) - d (T_i - T_ref). (The room's field is not the magnets' and
is scaled with them by mistake: 50 uT x 0.12 %/K x 10 K is 0.6 uT, a tenth of one LSB.)
The wrench is scaled by the stiffness at the sensor's mean temperature: w k(T) / k(T_ref).

What is not compensated grows with the distance from what was measured, and samples beyond
the span are flagged: the calibration's temperatures widened by `CALIBRATED_MARGIN_K` when
it measured the drift, else the reference widened by `LAWS_MARGIN_K`.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np

from ftsensord.calibration.thermal import CalibrationTemperature, ThermalLaws

#: Beyond the temperatures a calibration measured the drift at, a linear drift is
#: extrapolated; 2 K past them kept a sensor at rest within 0.05 N on the as-built parts of
#: benchmarks/accuracy/warm.py (docs/results/accuracy.md, "Warmth").
CALIBRATED_MARGIN_K = 2.0
#: With the laws alone, each chip's own offset drift (up to 2.5 uT/K on X and Y within the
#: datasheet's bound) stays: on benchmarks/accuracy/warm.py's parts, 0.05 N at rest is reached at
#: about 2 K from the reference (docs/results/accuracy.md, "Warmth").
LAWS_MARGIN_K = 1.5


class ThermalCompensation:
    """One sensor's temperature stage: its chips' last die temperatures (degC), the reference
    they are compensated to, and the factors that do it (`flux_scale`, `flux_shift`,
    `wrench_scale`, recomputed only when a temperature is read: a cycle costs three
    array operations).

    The reference is the calibration's mean temperature when it recorded one; else the
    temperature at the last tare, and before any tare the first one read (the tare absorbs
    whatever came before it).
    """

    name: ClassVar[str] = "temperature"

    def __init__(self, laws: ThermalLaws, chips: int, calibration: CalibrationTemperature | None = None):
        self.laws = laws
        #: Counts the changes of `flux_scale` and `flux_shift`: what is folded from them
        #: (`redundancy.RedundancyCheck`) is made again when it moves.
        self.version = 0
        self.calibration = calibration
        self.drift = None if calibration is None else calibration.drift_t_per_k
        self.celsius = np.full(chips, np.nan)
        self.reference_c: float | None = None if calibration is None else calibration.mean_c
        self.source = "none" if calibration is None else "calibration"
        self.flux_scale = np.ones(3 * chips)
        self.flux_shift = np.zeros(3 * chips)
        self.wrench_scale = 1.0
        self.beyond_span = False
        self.tare_c: float | None = None  # the chips' mean temperature at the last tare (degC)

    @property
    def span_c(self) -> tuple[float, float] | None:
        """The temperatures (degC) the compensation covers, or None before any is known."""
        c = self.calibration
        if c is not None and self.drift is not None:
            return c.lowest_c - CALIBRATED_MARGIN_K, c.highest_c + CALIBRATED_MARGIN_K
        if self.reference_c is None:
            return None
        lo, hi = (self.reference_c, self.reference_c) if c is None else (c.lowest_c, c.highest_c)
        return lo - LAWS_MARGIN_K, hi + LAWS_MARGIN_K

    def apply(self, flux: np.ndarray) -> np.ndarray:
        """Flux (T) as read, brought to the reference temperature."""
        return flux * self.flux_scale - self.flux_shift

    def observe(self, celsius: list[float | None]) -> None:
        """This cycle's die temperatures by chip (None: not read this cycle, or the chip
        did not answer: its last one stays)."""
        changed = False
        for i, c in enumerate(celsius):
            if c is not None and math.isfinite(c):
                self.celsius[i] = c
                changed = True
        if not changed:
            return
        if self.reference_c is None:
            self.reference_c = float(np.nanmean(self.celsius))
            self.source = "first reading"
        self._update()

    def tared(self, zero: np.ndarray) -> np.ndarray:
        """A tare: its temperature is kept (`status`); without a calibration temperature it
        becomes the reference. The ``zero`` is taken at it and compensated like every sample
        after it."""
        if np.isfinite(self.celsius).any():
            self.tare_c = float(np.nanmean(self.celsius))
            if self.calibration is None:
                self.reference_c = self.tare_c
                self.source = "tare"
                self._update()
        return self.apply(zero)

    def configure(self, rate_hz: float) -> None:
        pass  # the laws know no time

    def gap(self, periods: int) -> None:
        pass  # the last temperatures read stand until the next are

    def restart(self) -> None:
        pass  # nothing learnt from the estimate

    def _update(self) -> None:
        known = np.isfinite(self.celsius)
        ref = self.reference_c
        assert ref is not None  # set by the first reading
        now = np.where(known, self.celsius, ref)  # a chip never read: nothing to compensate
        self.flux_scale = (self.laws.flux_gain(np.array([ref])) / self.laws.flux_gain(now)).ravel()
        if self.drift is not None:
            self.flux_shift = self.drift * np.repeat(now - ref, 3)
        mean = float(now[known].mean())
        self.wrench_scale = self.laws.stiffness_gain(mean) / self.laws.stiffness_gain(ref)
        lo, hi = self.span_c  # type: ignore[misc]  # known once a reference is
        self.beyond_span = bool(np.any((now[known] < lo) | (now[known] > hi)))
        self.version += 1

    def status(self) -> dict[str, Any]:
        known = np.isfinite(self.celsius)
        span = self.span_c
        return {
            "reference_c": None if self.reference_c is None else round(self.reference_c, 2),
            "reference_from": self.source,
            "drift_calibrated": self.drift is not None,
            "tare_c": None if self.tare_c is None else round(self.tare_c, 2),
            "span_c": None if span is None else [round(span[0], 2), round(span[1], 2)],
            "mean_c": round(float(self.celsius[known].mean()), 2) if known.any() else None,
            "beyond_span": self.beyond_span,
            "laws": self.laws.document(),
        }
