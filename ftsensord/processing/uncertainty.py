"""Each wrench sample's 1-sigma per axis (N, Nm): what the daemon knows of its error.

Four independent parts, added as variances (docs/design/estimators.md, "Each sample's sigma"):

- the chips' reading noise (`pipeline.channel_sigma_t`, T, at their settings: the chip's noise
  and its LSB's quantisation) less the quantisation's undithered part (the third part), through
  the estimator used: M diag(sigma_t^2 - q^2) M^T, M = K A with every chip, K pinv(H_S) over
  the chips left (degraded), and for the nonlinear estimator its stiffness times the solve's
  gains (J_S^T J_S + P)^-1 J_S^T, J the flux model's Jacobian the solve keeps near its pose
  (`NonlinearEstimator.jacobian_at`); then times the filter's variance factor
  (`filters.variance_factors`), as this noise is independent from sample to sample. At the
  tare's own field the noise is the one its samples spread by (each channel's variance
  over them: at the longest conversions the chip's noise is a small part of an LSB and only
  the channels near a step toggle, so the noise over the fields is far off at any one), and
  a load moves each channel back to the noise over the fields (`_Maps.held_weights`);
- the tare's own noise: its zero is the mean of n samples, so that noise's M (...) M^T / n, an
  offset the filter does not shrink (none before a tare: the calibration's zero is the
  mean of hundreds of poses' samples, and its error is in the last part);
- the quantisation the chip's noise does not dither (`undithered`, q per channel): where the
  noise is not well above the LSB (at the packaged RES 3 the LSB is 6 uT on x and y against
  2 uT of noise; at the longest conversions 27 times the noise) the mean of a channel's
  readings at a held field is off the field by a sawtooth of it, the same at every sample:
  a bias of the load that no filter shrinks. After a tare the error is that bias at the load
  less the one at the tare's field: none at the tare's load, 2 q^2 a channel once the load
  has moved its field a fraction of an LSB (`Uncertainty.quantisation`); untared, q^2;
- the calibration's model error, learnt on its validation poses (`ModelError`), an error
  of the load, not of the sample: the filter does not shrink it either.

The noise parts are constant matrices for a given estimator, set of chips and tare (and the
nonlinear solve's kept Jacobian): built once and kept, keyed on the pipeline's `version` (its
tare), the chips and the kept Jacobian's version (`NonlinearEstimator.jacobian_at`), with what
they come to at the filter's variance factor and the quantisation's maps through the same M
beside them (`_Maps`), so a sample costs its model error's few products of six numbers and,
tared under a load, the quantisation's two. A moving load's nonlinear estimate keeps a new
Jacobian at nearly every sample: its maps then make at once only the variances per axis a
sample takes, the rest when asked. A sample without an estimate (invalid) or whose estimator
fell back has no known sigma: NaN.
"""

from __future__ import annotations

import math
import operator
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np

from ftsensord.model.linear import SENSOR_RANGE, LinearModel
from ftsensord.model.nonlinear import NonlinearEstimator

AXES = ("Fx", "Fy", "Fz", "Mx", "My", "Mz")
_SCALE = (1.0 / SENSOR_RANGE) ** 2
_POWERS = np.array([[1.0], [2.0], [4.0]])  # [|w|, w^2, w^4] as one power of |w| (3 x 6)


@dataclass(frozen=True)
class ModelError:
    """The calibration's error per axis as a function of the load w (N, Nm), from its report's
    ``error_model`` (`calibration.fit.error_model`): per axis k,

        error_k^2 ~ rest_k^2 + sum_j spread_kj |w_j| + sum_j (gain_kj w_j)^2
                    + sum_j (curvature_kj w_j^2)^2 + sum_j (beyond_kj max(0, |w_j| - within_j))^2,

    the last term zero within the calibration's range ``within`` (the check poses' errors beyond
    it), where the first terms are held at the range's edge (their curvature, fitted within it,
    would grow as w^4 beyond). Without a ``within`` (no loads beyond it were measured: the linear
    map's, whose estimate is flagged `extrapolated` there) the form runs on as fitted.

    Most of it is a bias, not noise: the same load reads the same error each time, and no
    filter or averaging shrinks it; over the loads of the calibration's range, the errors
    spread as this variance says. After a tare the error that stays at the tare's load is
    taken out: the load is counted from the tare's (exact for the gain term), and the rest
    term grows back with it, in full from the fitted loads' RMS range-scaled load
    (``mean_load``) on.

    ``source`` says what it came from: "flux model" (the linear map's error over the
    calibration's range, read through the calibration's flux model), "poses" (the errors on
    the poses the calibration holds), "validation" (an older file's validation poses, one
    coefficient per axis against the load's range-scaled norm), "validation_rmse" (older still:
    the validation RMS at every load), or "none" (no model error in the sigma)."""

    rest: np.ndarray  # (6,) N, Nm
    spread: np.ndarray  # (6, 6) error^2 per unit load, row: the axis in error
    gain: np.ndarray  # (6, 6) error per unit load
    curvature: np.ndarray  # (6, 6) error per unit load squared
    mean_load: float
    source: str
    beyond: np.ndarray = field(default_factory=lambda: np.zeros((6, 6)))  # per unit load past ``within``
    within: np.ndarray = field(
        default_factory=lambda: np.full(6, np.inf)
    )  # the range the first terms hold in
    _beyond2: np.ndarray = field(init=False, repr=False)
    _terms: np.ndarray = field(init=False, repr=False)
    _rest2: np.ndarray = field(init=False, repr=False)
    _resting: bool = field(init=False, repr=False)
    _bounded: bool = field(init=False, repr=False)
    _within: list[float] = field(init=False, repr=False)  # ``within`` as floats, for a sample's test
    _loaded: bool = field(init=False, repr=False)

    def __post_init__(self) -> None:
        # One 6 x 18 map on [|w|, w^2, w^4]: a sample's variance is one product.
        object.__setattr__(self, "_terms", np.hstack([self.spread, self.gain**2, self.curvature**2]))
        object.__setattr__(self, "_beyond2", self.beyond**2)
        object.__setattr__(self, "_rest2", self.rest**2)
        object.__setattr__(self, "_resting", bool(np.any(self.rest)))
        object.__setattr__(self, "_bounded", bool(np.all(np.isfinite(self.within))))
        object.__setattr__(self, "_within", self.within.tolist())
        object.__setattr__(
            self, "_loaded", bool(np.any(self.spread) or np.any(self.gain) or np.any(self.curvature))
        )

    @classmethod
    def from_report(cls, report: Mapping[str, Any] | None) -> ModelError:
        report = report or {}
        fitted = report.get("error_model")
        if isinstance(fitted, Mapping):
            return cls(
                np.array([float(fitted["rest"][a]) for a in AXES]),
                np.array([[float(v) for v in fitted["spread"][a]] for a in AXES]),
                np.array([[float(v) for v in fitted["gain"][a]] for a in AXES]),
                np.array([[float(v) for v in fitted["curvature"][a]] for a in AXES]),
                float(fitted.get("mean_load", 0.0)),
                str(fitted.get("source", "poses")),
                np.array([[float(v) for v in fitted.get("beyond", {}).get(a, [0.0] * 6)] for a in AXES]),
                np.full(6, np.inf)
                if fitted.get("within") is None
                else np.array([float(v) for v in fitted["within"]]),
            )
        older = report.get("validation_error")
        if isinstance(older, Mapping):
            # error^2 ~ rest^2 + (per_load |w / SENSOR_RANGE|)^2: a gain of per_load / range_j on
            # every axis j, exactly.
            per_load = np.array([float(older["per_load"][a]) for a in AXES])
            return cls(
                np.array([float(older["rest"][a]) for a in AXES]),
                np.zeros((6, 6)),
                per_load[:, None] / SENSOR_RANGE[None, :],
                np.zeros((6, 6)),
                float(older.get("mean_load", 0.0)),
                "validation",
            )
        none = np.zeros((6, 6))
        rmse = report.get("validation_rmse")
        if isinstance(rmse, Mapping):
            rest = np.array([float(rmse[a]) for a in AXES])
            return cls(rest, none, none, none, 0.0, "validation_rmse")
        return cls(np.zeros(6), none, none, none, 0.0, "none")

    def variance(
        self, wrench: np.ndarray, tare_wrench: np.ndarray, tared: bool, known: np.ndarray | None = None
    ) -> np.ndarray:
        """The model error's variance per axis at ``wrench`` (as published: after the tare's
        ``tare_wrench`` was taken off); ``known``: how far (6, N and Nm) each axis's reading may
        be off the load by its noise, taken off its size first (`NOISE_SIGMAS`)."""
        rest2 = self._rest2
        if not self._loaded:
            return rest2
        a = np.abs(wrench) if known is None else np.maximum(np.abs(wrench) - known, 0.0)
        beyond = None
        # The load on the sensor (the tare's included) past the range on an axis: six floats'
        # test (numpy's calls on six numbers would cost more than the rest of the sample), in
        # maps of builtins (no Python frame a value, as a generator's).
        if self._bounded and any(
            map(operator.gt, map(abs, map(operator.add, wrench.tolist(), tare_wrench.tolist())), self._within)
        ):  # the range's terms held at its edge, the last term grows from there
            past = np.abs(wrench + tare_wrench) - self.within
            a = np.minimum(a, self.within)
            beyond = self._beyond2 @ np.maximum(past, 0.0) ** 2
        powers = a**_POWERS  # [|w|; w^2; w^4]: one call for the three
        loaded = self._terms @ powers.ravel()
        if beyond is not None:
            loaded = loaded + beyond
        if not tared or not self._resting:
            return rest2 + loaded
        load = float(np.dot(powers[1], _SCALE))  # L^2, from the tare's load
        back = 1.0 if self.mean_load <= 0 else min(1.0, load / self.mean_load**2)
        return rest2 * back + loaded


def beyond_noise(wrench: np.ndarray, known: np.ndarray) -> np.ndarray:
    """The load (6, N and Nm) a reading ``wrench`` shows beyond ``known``, how far its noise
    may take it on each axis: what has moved the fields since the tare for certain."""
    return np.copysign(np.maximum(np.abs(wrench) - known, 0.0), wrench)


def propagate(M: np.ndarray, sigma_t: np.ndarray) -> np.ndarray:
    """M diag(sigma_t^2) M^T: the covariance (6 x 6) of M b for channels of noise ``sigma_t``."""
    return through(M, sigma_t**2)


def through(M: np.ndarray, variances: np.ndarray) -> np.ndarray:
    """M diag(variances) M^T: the covariance (6 x 6) of M b for independent channels of
    ``variances``."""
    return (M * variances) @ M.T


@dataclass(frozen=True, eq=False)
class SampleSigma:
    """A sample's sigma (6; NaN unknown) and the parts of its covariance (`covariance`)."""

    sigma: np.ndarray
    maps: _Maps | None = None  # the noise maps it was made with
    held: np.ndarray | None = None  # each channel's weight on the tare's own spread (`_Maps.held_weights`)
    model: np.ndarray | None = None  # the model error's and the undithered quantisation's variances (6)
    scale: float = 1.0
    factor: float = 1.0  # the filter's variance factor on the noise

    def covariance(self) -> np.ndarray:
        """The full 6 x 6 covariance (N, Nm squared); NaN where the sigma is unknown."""
        if self.maps is None or self.model is None:
            return np.full((6, 6), np.nan)
        noise = self.maps.noise_at(self.held)
        return (noise * self.factor + self.maps.offset + np.diag(self.model)) * self.scale**2


UNKNOWN = SampleSigma(np.full(6, np.nan))
UNKNOWN.sigma.setflags(write=False)


#: The model error is asked at the load less this many of the sample's noise sigma per axis: a
#: reading is the load to within its noise, and at rest the noise read as a load widened the
#: linear map's sigma (its spread term grows fastest near no load: Fy's samples at rest were
#: within 1 sigma 91 % of the time, 100 % with the filter on). 2: 95 % of the noise's draws.
NOISE_SIGMAS = 2.0


@dataclass(eq=False)
class _Maps:
    """One estimator's, set of chips' and tare's noise maps (`Uncertainty.maps`), all through M,
    how the estimate moves with each channel used (6 x channels): the noise over the fields
    (``channels``' independent noise), at the tare's own field where its spread is known
    (`held_weights`), the tare's, and the undithered quantisation's (`quantisation`; none when
    ``lsb_t`` tells none apart). Made together and dropped together, on a tare or a new kept
    Jacobian, as a moving load's nonlinear estimate keeps at nearly every sample: what each
    sample takes of them (their variances per axis) is made with them, the rest when first
    asked (the 6 x 6 covariances: the tip's; the per-channel maps: a tared load's). What a
    sample makes of them at the filter's variance factor is kept for the last factor: it holds
    once the filter has settled, so a sample makes only its model error's part."""

    M: np.ndarray
    channels: _Channels
    tare_samples: int | None  # how many samples the tare's zero averaged (None: its noise unknown)
    #: (channels) the tare's own samples' variance (T^2); None: not known (or too few samples)
    spread: np.ndarray | None = None
    diag: np.ndarray = field(init=False)  # one sample's noise variance per axis (`noise`'s diagonal)
    #: At the tare's field (`held_noise`'s diagonal); None without ``spread``
    held_diag: np.ndarray | None = field(init=False)
    offset_diag: np.ndarray = field(init=False)  # the tare's (`offset`'s diagonal)
    #: The undithered quantisation's variance untared, q^2 a channel (`quantisation`); None when
    #: ``lsb_t`` tells none apart
    bias_untared: np.ndarray | None = field(init=False)
    #: (factor, factor * the noise at the tare's field + offset_diag, NOISE_SIGMAS times its root)
    now: tuple[float, np.ndarray, np.ndarray] | None = None

    def __post_init__(self) -> None:
        squared = self.M * self.M
        # The variances per axis over the fields in one product: sum_c M_kc^2 (sigma_c^2, q_c^2).
        per_axis = self.channels.variances @ squared.T
        self.diag = per_axis[0]
        self.bias_untared = None if self.channels.bias_moves is None else per_axis[1]
        self.held_diag = None if self.spread is None else squared @ self.spread
        # The tare's mean is of its own samples: their spread where known.
        tare = self.diag if self.held_diag is None else self.held_diag
        self.offset_diag = tare / self.tare_samples if self.tare_samples else np.zeros(6)

    @property
    def expected(self) -> np.ndarray:
        """(channels) Each channel's noise variance the filter shrinks, over the fields (T^2)."""
        return self.channels.variances[0]

    @cached_property
    def noise(self) -> np.ndarray:
        """One sample's noise covariance (6 x 6) over the fields, of the noise the filter shrinks."""
        return through(self.M, self.expected)

    @cached_property
    def held_noise(self) -> np.ndarray:
        """`noise` at the tare's field (6 x 6), from ``spread``."""
        assert self.spread is not None
        return through(self.M, self.spread)

    @cached_property
    def held_shift(self) -> np.ndarray:
        """(6 x channels) M^2 (spread - expected): each channel's move from `held_diag` to `diag`."""
        assert self.spread is not None
        return self.M * self.M * (self.spread - self.expected)

    @cached_property
    def offset(self) -> np.ndarray:
        """The tare's noise covariance (6 x 6): its own samples' noise over their number."""
        if not self.tare_samples:
            return np.zeros((6, 6))
        return (self.noise if self.spread is None else self.held_noise) / self.tare_samples

    @cached_property
    def bias(self) -> np.ndarray:
        """(6 x channels) M^2 q^2: each channel's share of `bias_untared` on each axis."""
        return self.M * self.M * self.channels.variances[1]

    def at(self, factor: float) -> tuple[np.ndarray, np.ndarray]:
        """The noise's variance per axis at the filter's variance ``factor`` at the tare's field
        (the tare's spread where known), the tare's added, and `NOISE_SIGMAS` times its square
        root (the noise the model error is asked without)."""
        now = self.now
        if now is None or now[0] != factor:
            diag = self.diag if self.held_diag is None else self.held_diag
            variance = factor * diag + self.offset_diag
            now = self.now = (factor, variance, NOISE_SIGMAS * np.sqrt(variance))
        return now[1], now[2]

    def held_weights(self, wrench: np.ndarray, known: np.ndarray) -> np.ndarray | None:
        """Each channel's weight (channels) on the noise the tare measured at its field against
        the noise over the fields: exp(-z^2 / 2), z the field the load ``wrench`` less ``known``
        (its noise, as the model error's) has moved the channel by, in the chip's noise sigmas
        (a step of the LSB toggles a reading only within a few of them of its field: past
        them the toggling is another field's, as likely as any). None: the tare's field
        (every weight 1), or no spread known."""
        if self.spread is None:
            return None
        load = beyond_noise(wrench, known)
        if not load.any():
            return None
        z = self.channels.held_moves @ load
        return np.exp(-0.5 * z * z)

    def noise_diag(self, held: np.ndarray | None) -> np.ndarray:
        """One sample's noise variance per axis (6) at the channels' weights ``held``
        (`held_weights`: None at the tare's field)."""
        if self.held_diag is None:
            return self.diag
        if held is None:
            return self.held_diag
        return self.diag + self.held_shift @ held

    def noise_at(self, held: np.ndarray | None) -> np.ndarray:
        """`noise_diag`'s full covariance (6 x 6)."""
        if self.spread is None:
            return self.noise
        if held is None:
            return self.held_noise
        return through(self.M, self.expected + held * (self.spread - self.expected))

    def quantisation(
        self, wrench: np.ndarray, known: np.ndarray, tared: bool, moved: bool = False
    ) -> np.ndarray:
        """The undithered quantisation's variance per axis (6) at ``wrench`` (as published, after
        the tare): untared sum_c M_kc^2 q_c^2; after a tare each channel's bias at the load less
        the one at the tare's field, whose variance over the fields is 2 q^2 (1 - cos(2 pi d /
        LSB)) for a field moved by d: taken as 2 q^2 min(1, 2 pi^2 (d / LSB)^2), its small-d
        form up to its mean, d the field the load ``wrench`` less ``known`` (its noise, as the
        model error's) moves the channel by. ``moved``: as once a load has moved every channel's
        field an LSB or more, whatever ``wrench`` (the mean a load brings: what plans take)."""
        moves = self.channels.bias_moves
        if self.bias_untared is None or moves is None:
            return np.zeros(6)
        if not tared:
            return self.bias_untared
        if moved:
            return 2.0 * self.bias_untared
        load = beyond_noise(wrench, known)
        if not load.any():
            return np.zeros(6)
        d = moves @ load  # pi sqrt(2) d / LSB a channel
        return 2.0 * (self.bias @ np.minimum(1.0, d * d))


@dataclass(frozen=True, eq=False)
class _Channels:
    """A set of chips' channels and what its maps take of the chips' settings for them."""

    where: np.ndarray  # bool per channel: the chips' channels
    every: bool  # every chip's
    independent: np.ndarray  # their noise the filter shrinks (T, `Uncertainty.independent_t`)
    #: (2 x channels) that noise's variance over the fields and the undithered quantisation's,
    #: q^2 (T^2, `Uncertainty.bias_t` squared)
    variances: np.ndarray
    #: (channels x 6) a load's move of each field in LSBs, times pi sqrt(2) (`_Maps.quantisation`);
    #: None when no quantisation is told apart
    bias_moves: np.ndarray | None
    held_moves: np.ndarray  # (channels x 6) a load's move of each field, in the chip's noise sigmas


def undithered(noise: np.ndarray, lsb: np.ndarray) -> np.ndarray:
    """The RMS, over the fields a load sets, of the mean reading's error at a held field: the
    part of a rounding quantiser's error (LSB^2 / 12 in all) that Gaussian noise of ``noise``
    (same units, per channel) does not dither. The error of Q(b + n) against b is a sawtooth
    of b, sum_k (-1)^k lsb / (pi k) sin(2 pi k b / lsb); the noise multiplies its k-th
    harmonic's mean by exp(-2 pi^2 k^2 noise^2 / lsb^2), so its mean square over b is

        q^2 = sum_k (lsb / (pi k))^2 / 2 exp(-4 pi^2 k^2 (noise / lsb)^2),

    LSB^2 / 12 without noise, 0.15 uT of the packaged 6 uT LSB at its 2 uT noise, nothing once
    the noise reaches an LSB."""
    noise, lsb = np.broadcast_arrays(np.asarray(noise, dtype=float), np.asarray(lsb, dtype=float))
    # Each distinct (noise, LSB) once: a sensor's channels are its chips' three axes again and
    # again, and an accuracy plan makes this for every conversion setting.
    pairs, back = np.unique(np.stack([noise.ravel(), lsb.ravel()]), axis=1, return_inverse=True)
    noise_u, lsb_u = pairs
    k = np.arange(1, UNDITHERED_TERMS + 1)[:, None]
    ratio = np.divide(noise_u, lsb_u, out=np.zeros_like(lsb_u), where=lsb_u > 0)
    terms = (lsb_u / (np.pi * k)) ** 2 / 2 * np.exp(-4 * np.pi**2 * k**2 * ratio**2)
    return np.sqrt(terms.sum(axis=0))[back.ravel()].reshape(noise.shape)


#: The fewest samples whose spread a tare's noise maps take (`Uncertainty.maps`): a channel's
#: variance from n samples is off by sqrt(2 / (n - 1)), 20 % at 50, and the axes sum several
#: channels; fewer, and the noise over the fields is the better guess.
SPREAD_SAMPLES = 50

#: The harmonics `undithered` sums: without noise the tail past k is 1 / (2 pi^2 k) of LSB^2,
#: here 1e-5 of LSB^2 / 12.
UNDITHERED_TERMS = 5000


class Uncertainty:
    """One sensor's sigma: the chips' noise, its calibration's model error, and the maps.
    ``nonlinear``: the sensor's nonlinear estimator (its flux model and stiffness), or None;
    ``lsb_t``: each channel's LSB (T, `pipeline.channel_lsb_t`), of which ``sigma_t`` holds the
    quantisation (None: no quantisation told apart, all of ``sigma_t`` independent noise)."""

    def __init__(
        self,
        model: LinearModel,
        sigma_t: np.ndarray,
        report: Mapping[str, Any] | None,
        nonlinear: NonlinearEstimator | None,
        lsb_t: np.ndarray | None = None,
    ):
        self.sigma_t = sigma_t  # the chips' settings', for this object's life (new settings: a new pipeline)
        if lsb_t is None:
            self.lsb_t, self.bias_t = np.zeros_like(sigma_t), np.zeros_like(sigma_t)
            self.chip_noise_t = np.asarray(sigma_t, dtype=float)
        else:
            self.lsb_t = np.asarray(lsb_t, dtype=float)
            self.chip_noise_t = np.sqrt(np.maximum(sigma_t**2 - self.lsb_t**2 / 12, 0.0))
            self.bias_t = undithered(self.chip_noise_t, self.lsb_t)
        # What the filter shrinks: the reading noise less its undithered part.
        self.independent_t = np.sqrt(np.maximum(sigma_t**2 - self.bias_t**2, 0.0))
        self._quantised = bool(np.any(self.bias_t > 0))
        # Each channel's field per unit wrench (24 x 6): how far a load moves it.
        self._flux_per_wrench = np.linalg.pinv(model.KA)
        self.linear_error = ModelError.from_report(report)
        nl = (report or {}).get("nonlinear")
        self.nonlinear_error = ModelError.from_report(nl if isinstance(nl, Mapping) else None)
        self._model = model
        self._nonlinear = nonlinear
        self._cache: dict[tuple[int, str, bytes], _Maps] = {}
        self._version = -1
        #: Per set of chips (bool per chip, its bytes): what its maps take of the settings' alone.
        self._channels: dict[bytes, _Channels] = {}
        #: The nonlinear maps' Jacobian (`NonlinearEstimator.jacobian_at`) and its version.
        self._jacobian: tuple[tuple[object, int] | None, np.ndarray | None] = (None, None)

    def _nonlinear_map(self, J: np.ndarray, channels: np.ndarray | None) -> np.ndarray:
        """K [(J_S^T J_S + P)^-1 J_S^T] (its first 6 rows): how the solve's answer moves with the
        flux of ``channels`` (bool per channel; None: every one), J the flux model's Jacobian at
        the solve's pose with the background field's 3 columns (the solve estimates the field
        beside the pose, with its prior P: `NonlinearEstimator.gains`, with every chip the
        solve's own chord gains). Without those columns the noise of Fz and the torques came
        out at half the spread the solve gives."""
        assert self._nonlinear is not None
        return self._nonlinear.stiffness @ self._nonlinear.gains(J, channels)[:6]

    def _channels_of(self, chips: np.ndarray, used: bytes) -> _Channels:
        """What the maps of ``chips`` (bool per chip; ``used`` its bytes) take of the settings'
        alone, made once per set of chips."""
        found = self._channels.get(used)
        if found is None:
            where = np.repeat(chips, 3)
            independent = self.independent_t[where]
            bias_moves = None
            if self._quantised:  # (channels x 6): a load's move of each field, in LSBs, times pi sqrt(2)
                bias_moves = (
                    self._flux_per_wrench[where] * (np.pi * np.sqrt(2.0) / self.lsb_t[where])[:, None]
                )
            sigma_n = self.chip_noise_t[where]
            found = self._channels[used] = _Channels(
                where,
                bool(chips.all()),
                independent,
                np.array([independent**2, self.bias_t[where] ** 2]),
                bias_moves,
                self._flux_per_wrench[where] / np.where(sigma_n > 0, sigma_n, np.inf)[:, None],
            )
        return found

    def maps(
        self,
        version: int,
        estimator: str,
        chips: np.ndarray,
        tare_samples: int | None,
        pose: tuple[np.ndarray, np.ndarray] | None = None,
        spread: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """One sample's noise covariance, its diagonal, and the tare's covariance, for the
        estimator and ``chips`` (bool per chip) at the pipeline's ``version``; ``pose``: the
        nonlinear solve's pose T_0C and background field (T, {0}) (None: the estimator's last
        fit's, at rest before its first); ``spread``: the variance (T^2) of each channel over
        the tare's samples (None: unknown); None when the chips left do not see all six axes.
        The noise is the one over the fields, as once a load has moved them (`_Maps`)."""
        found = self._maps(version, estimator, chips, tare_samples, pose, spread)
        return None if found is None else (found.noise, found.diag, found.offset)

    def _maps(
        self,
        version: int,
        estimator: str,
        chips: np.ndarray,
        tare_samples: int | None,
        pose: tuple[np.ndarray, np.ndarray] | None,
        spread: np.ndarray | None = None,
    ) -> _Maps | None:
        """`maps`, kept: made once per version, estimator and chips (and the nonlinear solve's
        kept Jacobian, by its version); ``spread`` is the tare's, so the version's too."""
        if version != self._version:  # a tare or untare: the tare's part changes
            self._cache.clear()
            self._version = version
        J = None
        if estimator == "nonlinear" and self._nonlinear is not None:
            # The Jacobian the solve keeps (`NonlinearEstimator.jacobian_at`), made within
            # `JACOBIAN_REUSE_M`, 4 mrad and 10 uT of this pose: not one of the sigma's own. It
            # differs from the one at this very pose by up to that rule's drift, 3 % at p50 and
            # 6 % at most, and so may the noise's sigma: well within what a sigma is for (its
            # Monte Carlo holds to 12 %, tests/test_sigma.py), and it saves making the flux
            # model's Jacobian (a solve's cost again) on every sample the load moves. The maps
            # are made again when it is another one.
            here = (self._nonlinear.pose, self._nonlinear.background_t) if pose is None else pose
            made_of, J = self._nonlinear.jacobian_at(here[0], here[1], self._jacobian[0])
            if J is None:  # the one the maps are of
                J = self._jacobian[1]
            else:  # another one (its version's count is new): its maps made again
                for key in [k for k in self._cache if k[1] == "nonlinear"]:
                    del self._cache[key]
                self._jacobian = (made_of, J)
        used = chips.tobytes()
        key = (version, estimator, used)
        found = self._cache.get(key)
        if found is None:
            channels = self._channels_of(chips, used)
            try:
                if J is not None:
                    M = self._nonlinear_map(J, None if channels.every else channels.where)
                elif channels.every:
                    M = self._model.KA
                else:
                    M = self._model.map_from(chips)
            except (ValueError, np.linalg.LinAlgError):
                return None
            held = None
            if spread is not None and tare_samples and tare_samples >= SPREAD_SAMPLES:
                # The noise at the tare's field, as its samples spread: at the longest
                # conversions the chip's noise is a small part of an LSB and only the channels
                # whose field lies near a step of it toggle, a few a part, so the noise over the
                # fields is far off at any one (Mz's at rest a tenth of it on some parts).
                held = np.asarray(spread, dtype=float)[channels.where]
            found = self._cache[key] = _Maps(M, channels, tare_samples, held)  # kept, and dropped, together
        return found

    def quantisation(
        self, key: tuple[int, str, bytes], wrench: np.ndarray, known: np.ndarray, tared: bool
    ) -> np.ndarray:
        """The undithered quantisation's variance per axis (6) at ``wrench`` for the maps of
        ``key`` (version, estimator, the chips' bytes), as made (`_Maps.quantisation`); zeros
        when none are kept."""
        found = self._cache.get(key)
        return np.zeros(6) if found is None else found.quantisation(wrench, known, tared)

    def sample(
        self,
        version: int,
        estimator: str,
        chips: np.ndarray,
        wrench: np.ndarray,
        tare_wrench: np.ndarray,
        tared: bool,
        tare_samples: int | None,
        factor: float,
        scale: float = 1.0,
        pose: tuple[np.ndarray, np.ndarray] | None = None,
        spread: np.ndarray | None = None,
    ) -> SampleSigma:
        """The sigma of a sample estimated by ``estimator`` from ``chips``; ``wrench``: its
        estimate before the filter (for the model error's load); ``factor``: the filter's
        variance factor (`WrenchFilter.variance_factor`); ``scale``: what the wrench was
        multiplied by after the estimate (the temperature stage's); ``pose``: the nonlinear
        solve's pose and background field (`maps`); ``spread``: the tare's channels' variance."""
        maps = self._maps(version, estimator, chips, tare_samples, pose, spread)
        # math.isfinite on six floats: numpy's isfinite and all cost ten times as much.
        if maps is None or not all(map(math.isfinite, wrench.tolist())):
            return UNKNOWN
        noise_now, known = maps.at(factor)
        held = maps.held_weights(wrench, known)
        if held is not None:  # a load has moved the fields off the tare's: the noise there
            noise_now = factor * maps.noise_diag(held) + maps.offset_diag
        error = self.nonlinear_error if estimator == "nonlinear" else self.linear_error
        model = error.variance(wrench, tare_wrench, tared, known)
        if maps.bias_untared is not None:
            model = model + maps.quantisation(wrench, known, tared)
        variance = noise_now + model
        sigma = np.sqrt(variance) * scale if scale != 1.0 else np.sqrt(variance)
        # The covariance's parts kept as they are (the cached maps, not copies): only the tip
        # asks for it (`tip_sigma`), so a sample makes no 6 x 6 product.
        return SampleSigma(sigma, maps, held, model, scale, factor)

    def predicted(
        self,
        factor: float,
        tare_samples: int | None,
        estimator: str = "linear",
        loaded: bool = False,
        spread: np.ndarray | None = None,
    ) -> dict[str, Any]:
        """The sigma at rest of the current settings (every chip, no load), and its parts:
        for `status`; ``spread``: the tare's channels' variance (`maps`), the noise at rest.
        ``loaded``: as once a load has moved every channel's field: the noise over the fields,
        and the undithered quantisation a load brings (its mean over them: `quantisation`),
        which at the tare's load is not there: what `accuracy` plans on, as no averaging
        shrinks it."""
        chips = np.ones(len(self.sigma_t) // 3, dtype=bool)
        maps = self._maps(self._version, estimator, chips, tare_samples, None, spread)
        if maps is None:
            return {"sigma": None}
        noise_diag = maps.diag if loaded else maps.noise_diag(None)
        error = self.nonlinear_error if estimator == "nonlinear" else self.linear_error
        tared = tare_samples is not None
        model = error.variance(np.zeros(6), np.zeros(6), tared)
        model = model + maps.quantisation(np.zeros(6), np.zeros(6), tared, moved=loaded)
        sigma = np.sqrt(factor * noise_diag + maps.offset_diag + model)
        return {
            "sigma": [round(float(v), 7) for v in sigma],
            "noise": [round(math.sqrt(float(v)), 7) for v in factor * noise_diag],
            "model_error": error.source,
        }


def sigma_text(sigma: list[float]) -> str:
    """A sigma (6: N x3, Nm x3) as an operator reads it: "fx fy fz N, mx my mz mNm"."""
    return (
        " ".join(f"{v:.3g}" for v in sigma[:3])
        + " N, "
        + " ".join(f"{v * 1e3:.3g}" for v in sigma[3:])
        + " mNm"
    )


def tip_sigma(parts: list[tuple[np.ndarray, SampleSigma]]) -> np.ndarray:
    """The tool tip's sigma (6) from each sensor's transform X (6 x 6) and sigma: the
    sensors' errors independent, sum X C X^T; NaN when one sensor's is unknown."""
    total = np.zeros((6, 6))
    for X, s in parts:
        C = s.covariance()
        if not np.all(np.isfinite(C)):
            return np.full(6, np.nan)
        total += X @ C @ X.T
    return np.sqrt(np.diag(total))
