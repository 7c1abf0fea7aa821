"""One sensor's way from a cycle's chip results to a flagged, filtered wrench.

`SensorPipeline` stacks the sensor's flux (T, in chip order), decides which
chips are usable, estimates the wrench (N, Nm, in the sensor's frame) with
the chosen estimator, flags what the sample went through, and smooths it.
A failing chip's data never enter a wrench: a chip without new data gives its
previous reading (flagged stale), a chip that did not answer NaN (flagged
missing), a saturated chip its reading (flagged, not used).
"""

from __future__ import annotations

import functools
import math
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..acquire.health import ChipResult
from ..chip import mlx90393 as mlx
from ..errors import ChipRefusedError
from ..model import se3
from ..model.linear import SENSOR_RANGE, Consistency, LinearModel, chi2_quantile
from ..model.nonlinear import NonlinearEstimator
from . import wire
from .config import SensorConfig
from .filters import WrenchFilter
from .loop import STATS_WINDOW

#: A linear estimate is flagged `extrapolated` past this multiple of the calibration's
#: largest load on an axis: up to 1.5x no axis's error relative to the load has grown
#: 1.5-fold, by 3x one has nearly tripled (benchmarks/extrapolation.py, docs/calibration.md).
EXTRAPOLATION_MARGIN = 1.5
#: The redundancy check (`LinearModel.consistency`), two tests on the whitened residual:
#: the whole residual (chi-square, 3 n - 6 dof: any disagreement, e.g. a field two chips
#: see) and, per chip, how much it drops when that chip is left out (chi-square, 3 dof: the
#: likelihood-ratio test for one faulty chip, far more sensitive to one, as its 3 dof hold
#: less noise and a fifth of the model error), and the slow test below. Under noise alone a
#: sample fails any with these odds in all (half to the whole residual's test, a quarter to
#: each per-chip test, split among the chips): at
#: 2 sensors x 100 Hz a false alarm once in 58 days, and it costs one flagged sample
#: estimated from 7 chips.
CONSISTENCY_FALSE_ODDS = 1e-9
#: The linear model's own residual (whitened norm, in noise sigmas), which the noise
#: threshold is raised by: at most AT_REST + AT_RANGE * s^2 for a load s times the
#: calibration's largest (the largest ratio over the axes). Measured on the nominal scene
#: with both shipped calibrations (600 loads at each s, tests/test_consistency.py measures
#: it again). Whole residual: 2.0 at rest (the calibration's zero is 4 uT off the scene's),
#: 3.6 at s = 0.25, 6.4 at 0.5, 20.3 at 1, 48.5 at 1.5. Largest one-chip drop: 1.0 at
#: rest, 1.3 at 0.1, 1.9 at 0.25, 3.8 at 0.5, 11.3 at 1, 27.6 at 1.5. The bounds below
#: clear each by at least 11 %. A real sensor's calibration with a larger model error
#: needs larger ones.
MODEL_RESIDUAL_AT_REST, MODEL_RESIDUAL_AT_RANGE = 2.5, 26.0
CHIP_RESIDUAL_AT_REST, CHIP_RESIDUAL_AT_RANGE = 1.5, 13.0
#: With `stray_field = "gradient"` a third test: the estimated gradient (chi-square, 2 dof),
#: which takes half of the whole residual's odds. Its model allowance, measured the same way
#: (tests/test_stray.py, the larger of the two calibrations): 0.08 sigma at rest, 0.2 at
#: s = 0.1, 0.6 at 0.25, 1.9 at 0.5, 8.0 at 1, 18.4 at 1.5; the bounds clear each by 18 %.
GRADIENT_RESIDUAL_AT_REST, GRADIENT_RESIDUAL_AT_RANGE = 0.3, 9.5
#: A chip found disagreeing stays out (its samples flagged) until it has agreed this many
#: samples in a row at a looser limit, the noise's 1 % point: a stuck chip under a slow
#: load hovers at the threshold for a while, and in and out it would let samples through
#: that are nearly as wrong as the threshold allows.
REJOIN_SAMPLES, REJOIN_ODDS = 20, 1e-2
#: A third test, on each chip's drop summed over this many samples (chi-square, 3 x this
#: dof): a chip drifting off slowly (stuck under a slow load) is found at a third of the
#: disagreement one sample needs, before its error reaches 5 sigma of the wrench (one
#: sample's test lets through up to 0.64 sigma of wrench per unit of residual, 5.7 sigma
#: at its limit). Minkowski: |sum (noise + model)^2|^(1/2) <= |sum noise^2|^(1/2) +
#: sqrt(N) max|model|, so the odds hold. 10 samples: 0.1 s at 100 Hz.
SLOW_WINDOW = 10


def channel_sigma_t(settings: mlx.Settings, chips: int) -> np.ndarray:
    """Each channel's reading noise (T, chips x 3): the chip's noise and its LSB's
    quantisation (LSB^2 / 12), which at the paper's settings is as large."""
    per_axis = [np.hypot(settings.noise_ut(a), settings.sensitivity_ut(a) / np.sqrt(12)) * 1e-6 for a in "xyz"]
    return np.tile(per_axis, chips)


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
    # Gravity (m/s^2, sensor frame) over the tare's samples: zero untared, None unknown (`service.gravity`).
    tare_gravity: np.ndarray | None = field(default_factory=lambda: np.zeros(3))
    fallbacks: int = 0
    sigma_t: np.ndarray | None = None  # each channel's noise (T); None: the default chip settings'
    check: RedundancyCheck = field(default_factory=lambda: RedundancyCheck())
    estimate_s: deque[float] = field(default_factory=lambda: deque(maxlen=STATS_WINDOW))

    @classmethod
    def build(cls, s: SensorConfig, smoothing: WrenchFilter, max_missing_chips: int,
              settings: mlx.Settings | None = None) -> SensorPipeline:
        nl = s.calibration.nonlinear
        sigma_t = channel_sigma_t(settings or mlx.Settings(), len(s.addresses))
        if s.model.H is not None:  # no map built in the cycle of a fault
            s.model.build_maps(sigma_t, max_missing_chips)
        return cls(s, s.model, smoothing, max_missing_chips, np.full(3 * len(s.addresses), np.nan),
                   estimator=s.estimator, nonlinear=nl.estimator() if nl is not None else None,
                   zero_twist=nl.zero_twist.copy() if nl is not None else None, sigma_t=sigma_t)

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
        if valid and (np.abs(wrench) > SENSOR_RANGE).any():
            wflags |= wire.FLAG_OVERLOAD
        filtered, wflags = self.filter.update(wrench, wflags)  # a filtered wrench carries its inputs' flags
        return SensorSample(flux, flags, filtered, wflags, valid)

    def flux(self, results: dict[int, ChipResult]) -> tuple[np.ndarray, int, np.ndarray]:
        """The sensor's stacked flux (T), its flags, and which chips are usable."""
        rs = [results[a] for a in self.config.addresses]
        ms = [r.measurement for r in rs]
        if all(m is not None and not m.any_saturated for m in ms):  # the usual cycle: one stack, no loop
            flux = np.concatenate([m.field_t for m in ms])  # type: ignore[union-attr]
            self.last_flux[:] = flux
            return flux, 0, _every_chip(len(ms))
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
        two are missing or saturated, or disagree with the others (inconsistent);
        else NaN, flagged invalid."""
        usable, checked = self.check.chips(self, flux, usable)
        flags |= checked
        missing = len(usable) - int(np.count_nonzero(usable))
        few_missing = missing <= self.max_missing_chips
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
        if not missing:
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
        if fitted is not None and (np.abs(wrench + self.tare_wrench) > EXTRAPOLATION_MARGIN * fitted).any():
            flags |= wire.FLAG_EXTRAPOLATED
        return wrench, flags

    def tare(self, zero: np.ndarray, gravity: np.ndarray | None = None) -> np.ndarray:
        """Make ``zero`` (the mean no-load flux, T) the new zero; returns the wrench it removes.
        ``gravity``: the mean gravity (m/s^2, sensor frame) while it was measured, None if unknown."""
        self.tare_wrench = self.config.model.wrench(zero)
        self.tare_gravity = None if gravity is None else np.array(gravity, dtype=float)
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


@functools.lru_cache(maxsize=8)
def _every_chip(n: int) -> np.ndarray:
    """``n`` chips all usable (read-only: shared by every cycle that has them all)."""
    every = np.ones(n, dtype=bool)
    every.setflags(write=False)
    return every


def use_estimator(pipelines: list[SensorPipeline], estimator: str, sensor: str | None) -> dict[str, str]:
    """Switch ``sensor``'s (None: every) estimator; ValueError where a nonlinear one lacks
    its calibration. Returns each sensor's estimator."""
    chosen = [p for p in pipelines if sensor is None or p.name == sensor]
    lacking = [p.name for p in chosen if estimator == "nonlinear" and p.nonlinear is None]
    if lacking:
        raise ValueError(f"no nonlinear calibration for {', '.join(lacking)}")
    for p in chosen:
        p.use(estimator)
    return {p.name: p.estimator for p in pipelines}


def tip_wrench(samples: dict[str, SensorSample], poses: dict[str, np.ndarray]) -> tuple[np.ndarray, int]:
    """The wrench at the tool tip (N, Nm, tip frame): each sensor's moved from its pose
    in the tip frame (T_tip,s: f_tip = R f_s, m_tip = R m_s + p x R f_s) and summed, with
    every sensor's flags: the tip is as good as its worst sensor."""
    tip, flags = np.zeros(6), 0
    for name, T in poses.items():
        tip += _moved_from(np.asarray(T, dtype=float).tobytes()) @ samples[name].wrench
        flags |= samples[name].flags
    return tip, flags


@functools.lru_cache(maxsize=64)
def _moved_from(pose: bytes) -> np.ndarray:
    """The wrench transform from a sensor at ``pose`` in the tip frame (4 x 4 float64 as
    bytes, m): built once per pose, not every cycle."""
    X = se3.wrench_transform(np.frombuffer(pose).reshape(4, 4))
    X.setflags(write=False)  # shared by every cycle
    return X


class RedundancyCheck:
    """Which of a sensor's chips agree with one deflection (`LinearModel.consistency`),
    sample by sample, and which were found out and stay out until they agree again."""

    def __init__(self) -> None:
        self.inconsistent = 0  # samples flagged
        self.suspects: dict[int, int] = {}  # chip index: samples it has agreed since found out
        # The slow test's window: each sample's drops (one row a sample, in turn) and load.
        self.slow_drops = np.zeros((SLOW_WINDOW, 0))
        self.slow_loads = [0.0] * SLOW_WINDOW
        self.slow_count = 0  # samples in the window since it was last cleared
        self.slow_key = b""  # the chips the drops in the window were computed over

    def chips(self, p: SensorPipeline, flux: np.ndarray, usable: np.ndarray) -> tuple[np.ndarray, int]:
        """The chips to estimate from, and `inconsistent` (+ `degraded`) when the usable
        chips' residual is beyond noise and model error: the chip whose leaving explains
        it is left out if the rest then agree, else the sample is flagged as it stands."""
        n_usable = int(np.count_nonzero(usable))
        if len(usable) - n_usable > p.max_missing_chips:
            return usable, 0  # too few chips for any estimate: the sample is invalid as it stands
        if p.model.H is None or p.sigma_t is None or n_usable * 3 <= p.model.unknowns:
            return usable, 0  # no flux model or no redundancy left: nothing to check against
        c = p.model.consistency(flux, p.sigma_t, usable)
        out, n_out = usable, n_usable
        if self.suspects:
            out = usable.copy()
            rejoin = self._limits(p, self._load2(p, c), c.dof, 1, REJOIN_ODDS)[1] ** 2
            for chip in list(self.suspects):
                if not usable[chip]:
                    continue  # missing or saturated this cycle: no news of it
                drop = c.chi2 - c.chi2_without[chip]
                self.suspects[chip] = self.suspects[chip] + 1 if drop <= rejoin else 0
                if self.suspects[chip] >= REJOIN_SAMPLES:
                    del self.suspects[chip]
                else:
                    out[chip] = False
            n_out = int(np.count_nonzero(out))
            if n_out < n_usable:
                if len(out) - n_out > p.max_missing_chips:
                    return usable, wire.FLAG_INCONSISTENT  # too many out to estimate without them
                c = p.model.consistency(flux, p.sigma_t, out)
        if not math.isfinite(c.chi2):
            return out, 0
        load2 = self._load2(p, c)
        culprit = None if self._agree(p, c, load2, n_out) else c.culprit()
        if culprit is None:
            culprit = self._slow_culprit(c, out, n_out, load2)
        if culprit is None:
            return out, 0 if n_out == n_usable else wire.FLAG_INCONSISTENT | wire.FLAG_DEGRADED
        self.inconsistent += 1
        rest = out.copy()
        rest[culprit] = False
        if (~rest).sum() <= p.max_missing_chips and np.isfinite(c.chi2_without[culprit]):
            again = p.model.consistency(flux, p.sigma_t, rest)
            if self._agree(p, again, self._load2(p, again), n_out - 1):
                self.suspects[culprit] = 0
                return rest, wire.FLAG_INCONSISTENT | wire.FLAG_DEGRADED
        return out, wire.FLAG_INCONSISTENT

    def _agree(self, p: SensorPipeline, c: Consistency, load2: float, chips: int) -> bool:
        """Both tests (and the gradient's, when estimated) within their limits. |noise + model|
        <= |noise| + |model|, so the false-alarm odds stay within CONSISTENCY_FALSE_ODDS."""
        whole, one = self._limits(p, load2, c.dof, chips, CONSISTENCY_FALSE_ODDS)
        if c.gradient_dof:
            limit = (math.sqrt(chi2_quantile(c.gradient_dof, CONSISTENCY_FALSE_ODDS / 4))
                     + GRADIENT_RESIDUAL_AT_REST + GRADIENT_RESIDUAL_AT_RANGE * load2)
            if c.gradient_chi2 > limit ** 2:
                return False
        # The largest drop is chi2 - the smallest chi2 without (inf for a chip not to be left out).
        return c.chi2 <= whole ** 2 and c.chi2 - float(c.chi2_without.min()) <= one ** 2

    def _slow_culprit(self, c: Consistency, chips: np.ndarray, n: int, load2: float) -> int | None:
        """The chip whose drop summed over the last `SLOW_WINDOW` samples (over the same
        ``chips``, ``n`` of them) is beyond noise and model error, or None."""
        key = chips.tobytes()
        if key != self.slow_key:
            self.slow_drops = np.zeros((SLOW_WINDOW, len(chips)))
            self.slow_count = 0
            self.slow_key = key
        turn = self.slow_count % SLOW_WINDOW
        self.slow_drops[turn] = c.drop
        self.slow_loads[turn] = load2
        self.slow_count += 1
        if self.slow_count < SLOW_WINDOW:
            return None
        total = self.slow_drops.sum(axis=0)
        s2 = max(self.slow_loads)
        limit = math.sqrt(chi2_quantile(3 * SLOW_WINDOW, CONSISTENCY_FALSE_ODDS / (4 * n))) \
            + math.sqrt(SLOW_WINDOW) * (CHIP_RESIDUAL_AT_REST + CHIP_RESIDUAL_AT_RANGE * s2)
        if float(total.max()) <= limit ** 2:
            return None
        self.slow_count = 0
        return int(np.argmax(total))

    def _load2(self, p: SensorPipeline, c: Consistency) -> float:
        """The load's square, as a fraction of the calibration's largest (largest over the axes)."""
        fitted = p.config.calibration.wrench_range
        return float((np.abs(c.wrench + p.tare_wrench) / (fitted if fitted is not None else SENSOR_RANGE)).max()) ** 2

    def _limits(self, p: SensorPipeline, load2: float, dof: int, chips: int, odds: float) -> tuple[float, float]:
        """The limits (whitened norms) of the whole residual (``dof``) and of one chip's
        drop at the load ``load2`` (`_load2`): the noise's at ``odds`` (half to the whole,
        a quarter to one chip's, split among ``chips``; the last quarter is the slow
        test's) plus the model's own error at this load."""
        # With a gradient estimated, its test takes half of the whole residual's odds.
        whole_odds = odds / (4 if p.model.gradient is not None else 2)
        whole = math.sqrt(chi2_quantile(dof, whole_odds)) + MODEL_RESIDUAL_AT_REST + MODEL_RESIDUAL_AT_RANGE * load2
        one = math.sqrt(chi2_quantile(3, odds / (4 * chips))) + CHIP_RESIDUAL_AT_REST + CHIP_RESIDUAL_AT_RANGE * load2
        return whole, one
