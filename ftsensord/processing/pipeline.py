"""One sensor's way from a cycle's chip results to a flagged, filtered wrench.

`SensorPipeline` stacks the sensor's flux (T, in chip order), decides which
chips are usable, estimates the wrench (N, Nm, in the sensor's frame) with
the chosen estimator, flags what the sample went through, and smooths it.
A failing chip's data never enter a wrench: a chip without new data gives its
previous reading (flagged stale), a chip that did not answer NaN (flagged
missing), a saturated chip its reading (flagged, not used).
"""

from __future__ import annotations

import operator
import time
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ftsensord.acquire.health import ChipResult
from ftsensord.acquire.readings import Readings
from ftsensord.calibration.thermal import ThermalLaws
from ftsensord.chip import mlx90393 as mlx
from ftsensord.config.sensors import SensorConfig
from ftsensord.errors import ChipRefusedError
from ftsensord.model import se3
from ftsensord.model.linear import EXTRAPOLATION_MARGIN, SENSOR_RANGE, LinearModel
from ftsensord.model.nonlinear import NonlinearEstimator
from ftsensord.processing.creep import CreepCompensation
from ftsensord.processing.filters import WrenchFilter
from ftsensord.processing.redundancy import RedundancyCheck, count_missing, every_chip
from ftsensord.processing.stage import Stage
from ftsensord.processing.stray import WorldGradient
from ftsensord.processing.temperature import ThermalCompensation
from ftsensord.processing.uncertainty import UNKNOWN, SampleSigma, Uncertainty
from ftsensord.protocol import wire

#: Samples whose estimator CPU time `status` reports (mean, max): 10 s at 100 Hz, the loop's own
#: statistics' window.
ESTIMATE_WINDOW = 1000


def channel_sigma_t(settings: mlx.Settings, chips: int) -> np.ndarray:
    """Each channel's reading noise (T, chips x 3): the chip's noise and its LSB's
    quantisation (LSB^2 / 12), which at the paper's settings is as large."""
    per_axis = [
        np.hypot(settings.noise_ut(a), settings.sensitivity_ut(a) / np.sqrt(12)) * 1e-6 for a in "xyz"
    ]
    sigma = np.tile(per_axis, chips)
    sigma.setflags(write=False)  # shared by every sample's check, which keeps its maps by identity
    return sigma


def channel_lsb_t(settings: mlx.Settings, chips: int) -> np.ndarray:
    """Each channel's LSB (T, chips x 3) at ``settings``: what `uncertainty` needs to tell the part
    of `channel_sigma_t`'s quantisation the chip's noise does not dither (a bias at a held field)."""
    return np.tile([settings.sensitivity_ut(a) * 1e-6 for a in "xyz"], chips)


@dataclass
class SensorSample:
    """What one cycle made of one sensor: its flux (T) and wrench (N, Nm), each with its flags."""

    flux: np.ndarray
    flux_flags: int
    wrench: np.ndarray  # after the filter
    flags: int
    valid: bool  # an estimate was possible (the wrench is not NaN)
    sigma: SampleSigma = UNKNOWN  # the wrench's 1-sigma per axis (N, Nm; NaN unknown), `uncertainty`


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
    # Gravity (m/s^2, sensor frame) over the tare's samples: zero untared, None unknown (`processing.gravity`).
    tare_gravity: np.ndarray | None = field(default_factory=lambda: np.zeros(3))
    fallbacks: int = 0
    sigma_t: np.ndarray | None = None  # each channel's noise (T); None: the default chip settings'
    check: RedundancyCheck = field(default_factory=lambda: RedundancyCheck())
    estimate_s: deque[float] = field(default_factory=lambda: deque(maxlen=ESTIMATE_WINDOW))
    thermal: ThermalCompensation | None = None  # None: temperatures not read (temperature_every = 0)
    stray: WorldGradient | None = None  # stray_field = "world": a motor's gradient learnt as the tool turns
    creep: CreepCompensation = field(
        default_factory=lambda: CreepCompensation(None, 100.0)
    )  # the silicone's (`build`)
    #: Counts the changes of what the redundancy check folds from the pipeline itself (the
    #: model's zero, the tare's wrench): the fold is made again when it moves.
    version: int = 0
    uncertainty: Uncertainty | None = None  # each sample's sigma; None: not computed
    tare_samples: int | None = None  # how many samples the tare's zero averaged (None: unknown or untared)
    tare_spread: np.ndarray | None = None  # each channel's variance over them (T^2; None: unknown or untared)

    def __post_init__(self) -> None:
        fitted = self.config.calibration.wrench_range
        # The extrapolation test's limits as Python floats (N, Nm; None: no calibrated loads).
        self._extrapolation = None if fitted is None else (EXTRAPOLATION_MARGIN * fitted).tolist()
        self._every = every_chip(len(self.config.addresses))
        self._used: tuple[str, np.ndarray] | None = None  # the last estimate's estimator and chips

    @classmethod
    def build(
        cls,
        s: SensorConfig,
        smoothing: WrenchFilter,
        max_missing_chips: int,
        settings: mlx.Settings | None = None,
        thermal: bool = True,
        rate_hz: float = 100.0,
    ) -> SensorPipeline:
        """``thermal``: the chips' temperatures are read (`Config.temperature_every`), so
        the temperature stage compensates and flags (`processing.temperature`); ``rate_hz``: the loop's."""
        nl = s.calibration.nonlinear
        nonlinear = nl.estimator() if nl is not None else None
        sigma_t = channel_sigma_t(settings or mlx.Settings(), len(s.addresses))
        if s.model.H is not None:  # no map built in the cycle of a fault
            s.model.build_maps(sigma_t, max_missing_chips)
        return cls(
            s,
            s.model,
            smoothing,
            max_missing_chips,
            np.full(3 * len(s.addresses), np.nan),
            estimator=s.estimator,
            nonlinear=nonlinear,
            zero_twist=nl.zero_twist.copy() if nl is not None else None,
            sigma_t=sigma_t,
            thermal=ThermalCompensation(
                ThermalLaws.physical(settings), len(s.addresses), s.calibration.temperature
            )
            if thermal
            else None,
            stray=WorldGradient(s.calibration.model, sigma_t) if s.stray_field == "world" else None,
            creep=CreepCompensation(s.calibration.silicone, rate_hz),
            uncertainty=Uncertainty(
                s.model,
                sigma_t,
                s.calibration.report,
                nonlinear,
                channel_lsb_t(settings or mlx.Settings(), len(s.addresses)),
            ),
        )

    @property
    def name(self) -> str:
        return self.config.name

    @property
    def stages(self) -> tuple[Stage, ...]:
        """The stages this sensor runs, in the order they act (`STAGE_TYPES`)."""
        return tuple(s for s in (self.thermal, self.stray, self.creep) if s is not None)

    @property
    def wrench_range(self) -> np.ndarray | None:
        """The largest load of each axis the calibration saw (N, Nm; None: not recorded)."""
        return self.config.calibration.wrench_range

    def step(
        self, results: Mapping[int, ChipResult], base_flags: int = 0, R: np.ndarray | None = None
    ) -> SensorSample:
        """This cycle's sample from the chips' ``results`` (by address); ``base_flags``
        apply to every stream of the cycle (e.g. late); ``R``: the sensor's orientation
        (R_world,sensor; None: unknown), for the stray stage."""
        flux, flags, usable = self.flux(results)
        flags |= base_flags
        thermal = self.thermal
        # The usual sample (linear, every chip usable and agreeing): check and wrench in one product.
        usual = (
            self.check.usual(self, flux, usable)
            if self.estimator == "linear" and self.stray is None
            else None
        )
        scale = 1.0
        if usual is not None:
            wrench, wflags = usual[0], flags | (wire.FLAG_EXTRAPOLATED if usual[1] else 0)
            self._used = ("linear", self._every)
        else:
            self._used = None
            wrench, wflags = self._staged(flux if thermal is None else thermal.apply(flux), flags, usable, R)
        if thermal is not None:
            if thermal.wrench_scale != 1.0:  # (x 1.0 changes no number)
                scale = thermal.wrench_scale
                wrench = wrench * scale
            if thermal.beyond_span:
                wflags |= wire.FLAG_TEMPERATURE
        wrench = self.creep.apply(wrench, not wflags & _BREAKS_MEMORY)  # the silicone's creep undone
        valid = not wflags & wire.FLAG_INVALID
        # Axis by axis in C (maps of builtins, no Python frame a value); NaN: not over, as numpy.
        if valid and any(map(operator.gt, map(abs, wrench.tolist()), _RANGE)):
            wflags |= wire.FLAG_OVERLOAD
        own = wflags
        filtered, wflags = self.filter.update(wrench, wflags)  # a filtered wrench carries its inputs' flags
        return SensorSample(flux, flags, filtered, wflags, valid, self._sigma(filtered, own, valid, scale))

    def _sigma(self, wrench: np.ndarray, flags: int, valid: bool, scale: float) -> SampleSigma:
        """The sigma of this sample (`uncertainty`): unknown without an estimate or after a
        fall-back; ``wrench``: the sample as published, after the filter (the load its model
        error is asked at: the filter's output is nearer the load than one noisy estimate),
        ``flags`` the estimate's own."""
        used = self._used
        if self.uncertainty is None or used is None or not valid or flags & wire.FLAG_FALLBACK:
            return UNKNOWN
        return self.uncertainty.sample(
            self.version,
            used[0],
            used[1],
            wrench,
            self.tare_wrench,
            self.tared,
            self.tare_samples,
            self.filter.variance_factor(),
            scale,
            (self.nonlinear.pose, self.nonlinear.background_t)
            if used[0] == "nonlinear" and self.nonlinear is not None
            else None,
            self.tare_spread,
        )

    def flux(self, results: Mapping[int, ChipResult]) -> tuple[np.ndarray, int, np.ndarray]:
        """The sensor's stacked flux (T), its flags, and which chips are usable: every chip's
        reading, one stack when each was read and none saturated; else chip by chip, a stale
        chip's last reading, a missing one's NaN."""
        # A clean cycle (`Readings.clean`: each read, none saturated, no temperature) keeps its
        # fields in one array: the same stack is rows of it. (`type is`: an ABC's isinstance
        # costs more than the rest of this branch.)
        if type(results) is Readings and results.field is not None:
            flux = results.field[results.rows(self.config.addresses)].reshape(-1)
            self.last_flux[:] = flux
            return flux, 0, every_chip(len(self.config.addresses))
        ms = [results[a].measurement for a in self.config.addresses]
        if self.thermal is not None and any(m is not None and m.temperature_c is not None for m in ms):
            self.thermal.observe([None if m is None else m.temperature_c for m in ms])
        if all(m is not None and not m.any_saturated for m in ms):  # each read, none saturated: one stack
            flux = np.concatenate([m.field_t for m in ms])  # type: ignore[union-attr]
            self.last_flux[:] = flux
            return flux, 0, every_chip(len(ms))
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
            elif (
                isinstance(r.error, ChipRefusedError)
                and r.error.command == "RM"
                and np.all(np.isfinite(self.last_flux[part]))
            ):
                flux[part] = self.last_flux[part]
                usable[i] = True
                flags |= wire.FLAG_STALE
            else:
                flags |= wire.FLAG_CHIP_MISSING
        return flux, flags, usable

    def _staged(
        self, flux: np.ndarray, flags: int, usable: np.ndarray, R: np.ndarray | None
    ) -> tuple[np.ndarray, int]:
        """`estimate` of the flux as the stray stage corrects it (when there is one), which
        then learns from the sample: every chip read, nothing flagged that says the flux or
        the load is off the linear model (the in-plane gradient itself may be `inconsistent`)."""
        stray = self.stray
        if stray is None:
            return self.estimate(flux, flags, usable)
        stray.turn_to(R)
        corrected, changed = stray.apply(flux)
        wrench, wflags = self.estimate(corrected, flags, usable)
        fitted = self.wrench_range
        if (
            usable.all()
            and not wflags & _NOT_LEARNT
            and np.all(np.isfinite(wrench))
            and not (self.thermal is not None and self.thermal.beyond_span)
            and (fitted is None or bool(np.all(np.abs(wrench + self.tare_wrench) <= fitted)))
        ):
            stray.learn(flux)
        return wrench, wflags | (wire.FLAG_INCONSISTENT if changed else 0)

    def estimate(self, flux: np.ndarray, flags: int, usable: np.ndarray) -> tuple[np.ndarray, int]:
        """The wrench from every chip; from the usable ones (degraded) when one or
        two are missing or saturated, or disagree with the others (inconsistent);
        else NaN, flagged invalid."""
        usable, checked = self.check.chips(self, flux, usable)
        flags |= checked
        missing = count_missing(usable)
        few_missing = missing <= self.max_missing_chips
        if self.estimator == "nonlinear" and self.nonlinear is not None and self.zero_twist is not None:
            if few_missing:
                t0 = time.process_time()
                e = self.nonlinear.estimate(flux, usable)
                self.estimate_s.append(time.process_time() - t0)
                if e.converged:
                    w = self.nonlinear.stiffness @ (e.xi - self.zero_twist)
                    self._used = ("nonlinear", usable)
                    return w, flags | (0 if usable.all() else wire.FLAG_DEGRADED)
            self.fallbacks += 1
            flags |= wire.FLAG_FALLBACK
        if not missing:
            self._used = ("linear", self._every)
            return self._linear(self.model.wrench(flux), flags)
        if few_missing and self.model.H is not None:
            try:
                w = self.model.wrench_from(flux, usable)
                self._used = ("linear", usable)
                return self._linear(w, flags | wire.FLAG_DEGRADED)
            except ValueError:
                pass  # the chips left do not see all six axes
        return np.full(6, np.nan), flags | wire.FLAG_INVALID

    def _linear(self, wrench: np.ndarray, flags: int) -> tuple[np.ndarray, int]:
        """A linear estimate, flagged `extrapolated` where the load on the sensor (the
        wrench plus what a tare removed) is beyond the calibration's loads."""
        limits = self._extrapolation
        # Over six Python floats, in C (maps of builtins): four numpy calls on six values cost more.
        if limits is not None and any(
            map(operator.gt, map(abs, map(operator.add, wrench.tolist(), self.tare_wrench.tolist())), limits)
        ):
            flags |= wire.FLAG_EXTRAPOLATED
        return wrench, flags

    def tare(
        self,
        zero: np.ndarray,
        gravity: np.ndarray | None = None,
        samples: int | None = None,
        spread: np.ndarray | None = None,
    ) -> np.ndarray:
        """Make ``zero`` (the mean no-load flux, T, as read) the new zero; returns the wrench it
        removes. ``gravity``: the mean gravity (m/s^2, sensor frame) while it was measured, None if
        unknown; ``samples``: how many samples ``zero`` averaged (for the sigma; None: unknown,
        and the tare's own noise is left out of it); ``spread``: each channel's variance over
        them (T^2, for the sigma's noise at the tare's field; None: unknown). With the temperature stage, the zero is
        taken at the tare's temperature and compensated like every sample after it."""
        for stage in self.stages:
            zero = stage.tared(zero)
        self.tare_wrench = self.config.model.wrench(zero)
        self.tare_gravity = None if gravity is None else np.array(gravity, dtype=float)
        self.model = self.model.with_zero(zero)
        if self.nonlinear is not None:
            e = self.nonlinear.estimate(zero)
            if e.converged:
                self.zero_twist = e.xi
        self.filter.reset()
        self.tared = True
        self.tare_samples = samples
        self.tare_spread = None if spread is None else np.array(spread, dtype=float)
        self.version += 1
        return self.tare_wrench

    def untare(self) -> None:
        """Back to the calibration's own zero."""
        self.model = self.config.model
        self.tare_wrench = np.zeros(6)
        self.tare_gravity = np.zeros(3)
        nl = self.config.calibration.nonlinear
        self.zero_twist = nl.zero_twist.copy() if nl is not None else None
        self.tared = False
        self.tare_samples = None
        self.tare_spread = None
        self.filter.reset()
        self.version += 1

    def use(self, estimator: str) -> None:
        """Switch the estimator ("linear" or "nonlinear"); the filter restarts."""
        if estimator == "nonlinear" and self.nonlinear is None:
            raise ValueError(f"no nonlinear calibration for {self.name}")
        self.estimator = estimator
        self.filter.reset()
        for stage in self.stages:
            stage.restart()

    def configure(self, averaging: int, lowpass_hz: float, rate_hz: float) -> None:
        """New loop settings: the filter's (restarted) and each stage's."""
        self.filter.configure(averaging, lowpass_hz, rate_hz)
        for stage in self.stages:
            stage.configure(rate_hz)

    def gap(self, periods: int) -> None:
        """``periods`` cycles made no sample (`stage.Stage.gap`): the filter's memory says
        nothing of the load now, and restarts; each stage keeps or drops its own."""
        self.filter.reset()
        for stage in self.stages:
            stage.gap(periods)

    def stages_status(self) -> dict[str, dict[str, Any] | None]:
        """Each stage's part of the sensor's `status`, by its name; None where it is off."""
        running = {type(s): s for s in self.stages}
        return {
            kind.name: (s.status() if (s := running.get(kind)) is not None else None) for kind in STAGE_TYPES
        }


_RANGE = SENSOR_RANGE.tolist()  # the overload test's limits as Python floats (N, Nm)

#: The stages a pipeline may run, in the order they act on a sample (`stage.Stage`).
STAGE_TYPES: tuple[type[Stage], ...] = (ThermalCompensation, WorldGradient, CreepCompensation)


#: Flags of a sample the stray stage does not learn from: a chip not read or left out, a
#: load beyond the linear model (a temperature beyond its span is asked of the stage itself).
_NOT_LEARNT = (
    wire.FLAG_CHIP_MISSING
    | wire.FLAG_SATURATED
    | wire.FLAG_STALE
    | wire.FLAG_DEGRADED
    | wire.FLAG_INVALID
    | wire.FLAG_EXTRAPOLATED
)


#: Flags of a sample kept out of the silicone stage's history (compensated from it without
#: entering it): a chip not read, stale or left out, no estimate, a fallback to the other estimator.
_BREAKS_MEMORY = (
    wire.FLAG_CHIP_MISSING
    | wire.FLAG_SATURATED
    | wire.FLAG_STALE
    | wire.FLAG_DEGRADED
    | wire.FLAG_INVALID
    | wire.FLAG_FALLBACK
    | wire.FLAG_INCONSISTENT
)


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


def tip_moves(poses: dict[str, np.ndarray]) -> list[tuple[str, np.ndarray]]:
    """Each sensor's wrench transform to the tool tip, X(T_tip,s), from its pose in the tip
    frame (4 x 4, m): f_tip = R f_s, m_tip = R m_s + p x R f_s; built once per configuration."""
    return [(name, se3.wrench_transform(np.asarray(T, dtype=float))) for name, T in poses.items()]


def tip_wrench(
    samples: dict[str, SensorSample], moves: list[tuple[str, np.ndarray]]
) -> tuple[np.ndarray, int]:
    """The wrench at the tool tip (N, Nm, tip frame): each sensor's moved by its `tip_moves`
    transform and summed, with every sensor's flags: the tip is as good as its worst sensor."""
    tip, flags = None, 0
    for name, X in moves:
        s = samples[name]
        moved = X @ s.wrench
        tip = moved if tip is None else tip + moved
        flags |= s.flags
    return (np.zeros(6) if tip is None else tip), flags
