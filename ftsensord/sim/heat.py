"""Heat in the scene: a sensor's temperature over time, and each chip's drift with it.

A sensor has one temperature (magnets, silicone and chips' dies alike: the part is a few
grams and a hand warms it over minutes); `TemperatureProfile` gives it at any time. Each
chip's sensitivity and offset drift by its own coefficients (`ChipDrift`), which the
emulated chip applies itself, choosing by its TCMP_EN bit as a real chip does. The laws and
their sources are in docs/design/physics.md ("Temperature").
"""

from __future__ import annotations

import functools
import math
from bisect import bisect_right
from dataclasses import dataclass

import numpy as np

from ftsensord.chip import mlx90393 as mlx


@dataclass(frozen=True)
class TemperatureProfile:
    """A sensor's temperature (degC) against time (s): ``celsius`` at ``times_s``, linear
    between and held at the ends, plus ``drift_c_per_s`` times t."""

    times_s: tuple[float, ...]
    celsius: tuple[float, ...]
    drift_c_per_s: float = 0.0

    def __post_init__(self) -> None:
        if not self.times_s or len(self.times_s) != len(self.celsius):
            raise ValueError(f"{len(self.celsius)} temperatures for {len(self.times_s)} times")
        if any(b <= a for a, b in zip(self.times_s, self.times_s[1:])):
            raise ValueError("times must be strictly increasing")
        if not all(math.isfinite(v) for v in (*self.times_s, *self.celsius, self.drift_c_per_s)):
            raise ValueError("times and temperatures must be finite")

    @classmethod
    def constant(cls, celsius: float) -> TemperatureProfile:
        return cls((0.0,), (celsius,))

    @classmethod
    def linear(cls, celsius: float, drift_c_per_s: float) -> TemperatureProfile:
        """``celsius`` at t = 0, changing by ``drift_c_per_s`` (degC/s)."""
        return cls((0.0,), (celsius,), drift_c_per_s)

    @functools.cached_property
    def is_reference(self) -> bool:
        """Held at the datasheet's 25 degC: nothing drifts, and the scene skips every law."""
        return self.drift_c_per_s == 0.0 and all(c == mlx.TEMPERATURE_REF_C for c in self.celsius)

    def at(self, t: float) -> float:
        """Temperature (degC) at ``t`` (s)."""
        times, values = self.times_s, self.celsius
        if len(times) == 1:  # constant or linear: asked at every conversion, so no search
            return values[0] + self.drift_c_per_s * t
        i = bisect_right(times, t)
        if i == 0:
            value = values[0]
        elif i == len(times):
            value = values[-1]
        else:
            w = (t - times[i - 1]) / (times[i] - times[i - 1])
            value = values[i - 1] + w * (values[i] - values[i - 1])
        return value + self.drift_c_per_s * t


@dataclass(frozen=True)
class ChipDrift:
    """One chip's drift with temperature, per axis (x, y, z) of its frame, from 25 degC.

    ``sensitivity_per_k``: relative change of its readings per K with TCMP_EN = 0;
    ``sensitivity_tcmp_per_k``: what is left of it with TCMP_EN = 1; ``offset_t_per_k``:
    the reading at zero field, T per K (TCMP_EN does not compensate it).
    """

    sensitivity_per_k: np.ndarray
    sensitivity_tcmp_per_k: np.ndarray
    offset_t_per_k: np.ndarray

    @classmethod
    def typical(cls) -> ChipDrift:
        """A chip at the datasheet's figures: the typical TC-off drift, and for the
        compensated drift and the offset, which the datasheet gives only as bounds, the
        bound itself (a chip within spec may sit there: the strict choice)."""
        return cls(
            np.array(mlx.SENSITIVITY_TEMPCO_PER_K),
            np.full(3, mlx.SENSITIVITY_TEMPCO_TCMP_PER_K),
            np.array(mlx.OFFSET_DRIFT_UT_PER_K) * 1e-6,
        )

    @classmethod
    def draw(cls, rng: np.random.Generator, n_chips: int) -> list[ChipDrift]:
        """``n_chips`` parts drawn from the datasheet's spread, in a fixed order: TC-off drift
        normal about the typical (`mlx.SENSITIVITY_TEMPCO_SPREAD_PER_K`), then compensated
        drift and offset uniform within their bounds (a band says nothing of its shape)."""
        sens = (
            np.array(mlx.SENSITIVITY_TEMPCO_PER_K)
            + rng.normal(0.0, 1.0, (n_chips, 3)) * mlx.SENSITIVITY_TEMPCO_SPREAD_PER_K
        )
        tcmp = rng.uniform(-1.0, 1.0, (n_chips, 3)) * mlx.SENSITIVITY_TEMPCO_TCMP_PER_K
        offset = rng.uniform(-1.0, 1.0, (n_chips, 3)) * np.array(mlx.OFFSET_DRIFT_UT_PER_K) * 1e-6
        return [cls(sens[i], tcmp[i], offset[i]) for i in range(n_chips)]

    def reading(self, field_t: np.ndarray, delta_k: float, tcmp: bool) -> np.ndarray:
        """What the Hall plates and ADC make of ``field_t`` (T, chip frame) ``delta_k``
        kelvin above 25 degC, with the chip's compensation on or off."""
        sensitivity = self.sensitivity_tcmp_per_k if tcmp else self.sensitivity_per_k
        return field_t * (1.0 + sensitivity * delta_k) + self.offset_t_per_k * delta_k
