"""Each wrench sample's 1-sigma per axis (N, Nm): what the daemon knows of its error.

Four independent parts, added as variances (docs/design/estimators.md, "Each sample's sigma"):

- the chips' reading noise (`pipeline.channel_sigma_t`, T, at their settings: the chip's noise
  and its LSB's quantisation) less the quantisation's undithered part (the third part), through
  the estimator used: M diag(sigma_t^2 - q^2) M^T, M = K A with every chip, K pinv(H_S) over
  the chips left (degraded), and for the nonlinear estimator its stiffness times the flux
  model's Jacobian at rest, pinv(H) (the solve's own Jacobian at the deflection is not used);
  then times the filter's variance factor (`filters.variance_factors`), as this noise is
  independent from sample to sample;
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

The noise parts are constant matrices for a given estimator, set of chips and tare: built
once and kept, keyed on the pipeline's `version` (its tare) and the chips, so a sample costs
a few products of six numbers. A sample without an estimate (invalid) or whose estimator
fell back has no known sigma: NaN.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ftsensord.model.linear import SENSOR_RANGE, LinearModel
from ftsensord.model.nonlinear import PRIOR_EYE, NonlinearEstimator

AXES = ("Fx", "Fy", "Fz", "Mx", "My", "Mz")
_SCALE = (1.0 / SENSOR_RANGE) ** 2


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
    _loaded: bool = field(init=False, repr=False)

    def __post_init__(self) -> None:
        # One 6 x 18 map on [|w|, w^2, w^4]: a sample's variance is one product.
        object.__setattr__(self, "_terms", np.hstack([self.spread, self.gain**2, self.curvature**2]))
        object.__setattr__(self, "_beyond2", self.beyond**2)
        object.__setattr__(self, "_rest2", self.rest**2)
        object.__setattr__(self, "_resting", bool(np.any(self.rest)))
        object.__setattr__(self, "_bounded", bool(np.all(np.isfinite(self.within))))
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
        if self._bounded:
            past = np.abs(wrench + tare_wrench) - self.within  # the load on the sensor, tare's included
            if np.any(past > 0):  # the range's terms held at its edge, the last term grows from there
                a = np.minimum(a, self.within)
                beyond = self._beyond2 @ np.maximum(past, 0.0) ** 2
        w2 = a * a
        loaded = self._terms @ np.concatenate((a, w2, w2 * w2))
        if beyond is not None:
            loaded = loaded + beyond
        if not tared or not self._resting:
            return rest2 + loaded
        load = float(np.dot(w2, _SCALE))  # L^2, from the tare's load
        back = 1.0 if self.mean_load <= 0 else min(1.0, load / self.mean_load**2)
        return rest2 * back + loaded


def propagate(M: np.ndarray, sigma_t: np.ndarray) -> np.ndarray:
    """M diag(sigma_t^2) M^T: the covariance (6 x 6) of M b for channels of noise ``sigma_t``."""
    return (M * sigma_t**2) @ M.T


@dataclass(frozen=True, eq=False)
class SampleSigma:
    """A sample's sigma (6; NaN unknown) and the parts of its covariance (`covariance`)."""

    sigma: np.ndarray
    noise: np.ndarray | None = None  # one sample's noise covariance (6 x 6), before the filter
    offset: np.ndarray | None = None  # the tare's (6 x 6)
    model: np.ndarray | None = None  # the model error's and the undithered quantisation's variances (6)
    scale: float = 1.0
    factor: float = 1.0  # the filter's variance factor on ``noise``

    def covariance(self) -> np.ndarray:
        """The full 6 x 6 covariance (N, Nm squared); NaN where the sigma is unknown."""
        if self.noise is None or self.offset is None or self.model is None:
            return np.full((6, 6), np.nan)
        return (self.noise * self.factor + self.offset + np.diag(self.model)) * self.scale**2


UNKNOWN = SampleSigma(np.full(6, np.nan))
UNKNOWN.sigma.setflags(write=False)


#: The model error is asked at the load less this many of the sample's noise sigma per axis: a
#: reading is the load to within its noise, and at rest the noise read as a load widened the
#: linear map's sigma (its spread term grows fastest near no load: Fy's samples at rest were
#: within 1 sigma 91 % of the time, 100 % with the filter on). 2: 95 % of the noise's draws.
NOISE_SIGMAS = 2.0
#: The nonlinear map is made again when the solve's pose has moved this far (m, rad) from the
#: one it was made at: the estimator's own bound for reusing a Jacobian
#: (`model.nonlinear.JACOBIAN_REUSE_M`, 4 mrad), within which the flux model's Jacobian changes
#: by about 3 % (so does the noise's sigma); at rest the map is made once.
NONLINEAR_MOVE_M, NONLINEAR_MOVE_RAD = 40e-6, 4e-3


def undithered(noise: np.ndarray, lsb: np.ndarray) -> np.ndarray:
    """The RMS, over the fields a load sets, of the mean reading's error at a held field: the
    part of a rounding quantiser's error (LSB^2 / 12 in all) that Gaussian noise of ``noise``
    (same units, per channel) does not dither. The error of Q(b + n) against b is a sawtooth
    of b, sum_k (-1)^k lsb / (pi k) sin(2 pi k b / lsb); the noise multiplies its k-th
    harmonic's mean by exp(-2 pi^2 k^2 noise^2 / lsb^2), so its mean square over b is

        q^2 = sum_k (lsb / (pi k))^2 / 2 exp(-4 pi^2 k^2 (noise / lsb)^2),

    LSB^2 / 12 without noise, 0.15 uT of the packaged 6 uT LSB at its 2 uT noise, nothing once
    the noise reaches an LSB."""
    noise, lsb = np.asarray(noise, dtype=float), np.asarray(lsb, dtype=float)
    k = np.arange(1, UNDITHERED_TERMS + 1)[:, None]
    ratio = np.divide(noise, lsb, out=np.zeros_like(lsb), where=lsb > 0)
    terms = (lsb / (np.pi * k)) ** 2 / 2 * np.exp(-4 * np.pi**2 * k**2 * ratio**2)
    return np.sqrt(terms.sum(axis=0))


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
        self.sigma_t = sigma_t
        if lsb_t is None:
            self.lsb_t, self.bias_t = np.zeros_like(sigma_t), np.zeros_like(sigma_t)
        else:
            self.lsb_t = np.asarray(lsb_t, dtype=float)
            chip_noise = np.sqrt(np.maximum(sigma_t**2 - self.lsb_t**2 / 12, 0.0))
            self.bias_t = undithered(chip_noise, self.lsb_t)
        # What the filter shrinks: the reading noise less its undithered part.
        self.independent_t = np.sqrt(np.maximum(sigma_t**2 - self.bias_t**2, 0.0))
        self._quantised = bool(np.any(self.bias_t > 0))
        # Each channel's field per unit wrench (24 x 6): how far a load moves it, in LSBs.
        self._flux_per_wrench = np.linalg.pinv(model.KA) if self._quantised else None
        self._bias_maps: dict[tuple[int, str, bytes], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self.linear_error = ModelError.from_report(report)
        nl = (report or {}).get("nonlinear")
        self.nonlinear_error = ModelError.from_report(nl if isinstance(nl, Mapping) else None)
        self._model = model
        self._nonlinear = nonlinear
        self._cache: dict[tuple[int, str, bytes], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._version = -1
        self._anchor: tuple[np.ndarray, np.ndarray] | None = None  # the pose and field of the nonlinear maps
        self._anchor_rows: list[float] = []  # its T's top 3 rows, as `_moved` compares them

    def _nonlinear_map(self, channels: np.ndarray, pose: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray:
        """K [(J_S^T J_S + P)^-1 J_S^T] (its first 6 rows): how the solve's answer moves with the
        flux of the channels used, J the flux model's Jacobian at the solve's pose with the
        background field's 3 columns (the solve estimates the field beside the pose, with its
        prior P: `model.nonlinear._normal`). Without those columns the noise of Fz and the
        torques came out at half the spread the solve gives."""
        assert self._nonlinear is not None
        T, u = pose if pose is not None else (np.eye(4), np.zeros(3))
        J = self._nonlinear.model.predict_and_jacobian(T, u, background=True)[1][channels]
        N = J.T @ J
        N[6:, 6:] += PRIOR_EYE
        return self._nonlinear.stiffness @ np.linalg.solve(N, J.T)[:6]

    def _moved(self, pose: tuple[np.ndarray, np.ndarray] | None) -> bool:
        """The solve's pose is off the one the nonlinear maps were made at (`NONLINEAR_MOVE_M`:
        its position's, and its rotation matrix's entries, which move by at most the angle)."""
        if pose is None:
            return self._anchor is None
        if self._anchor is None:
            return True
        # Twelve Python floats (the 3 x 4 top of T), not numpy's calls on a 4 x 4: a sample's check costs 2 us.
        now, then = pose[0][:3].ravel().tolist(), self._anchor_rows
        turned = max(abs(now[i] - then[i]) for i in (0, 1, 2, 4, 5, 6, 8, 9, 10))
        shifted = max(abs(now[i] - then[i]) for i in (3, 7, 11))
        return shifted > NONLINEAR_MOVE_M or turned > NONLINEAR_MOVE_RAD

    def maps(
        self,
        version: int,
        estimator: str,
        chips: np.ndarray,
        tare_samples: int | None,
        pose: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """One sample's noise covariance, its diagonal, and the tare's covariance, for the
        estimator and ``chips`` (bool per chip) at the pipeline's ``version``; ``pose``: the
        nonlinear solve's pose T_0C and background field (T, {0}) (None: at rest); None when
        the chips left do not see all six axes."""
        if version != self._version:  # a tare or untare: the tare's part changes
            self._cache.clear()
            self._bias_maps.clear()
            self._version = version
        nonlinear = estimator == "nonlinear" and self._nonlinear is not None
        if nonlinear and self._moved(pose):
            for key in [k for k in self._cache if k[1] == "nonlinear"]:
                del self._cache[key]
                self._bias_maps.pop(key, None)
            self._anchor = (np.eye(4), np.zeros(3)) if pose is None else (pose[0].copy(), pose[1].copy())
            self._anchor_rows = self._anchor[0][:3].ravel().tolist()
        key = (version, estimator, chips.tobytes())
        found = self._cache.get(key)
        if found is None:
            channels = np.repeat(chips, 3)
            try:
                if nonlinear:
                    M = self._nonlinear_map(channels, self._anchor)
                elif chips.all():
                    M = self._model.KA
                else:
                    M = self._model.map_from(chips)
            except (ValueError, np.linalg.LinAlgError):
                return None
            noise = propagate(M, self.independent_t[channels])
            offset = noise / tare_samples if tare_samples else np.zeros((6, 6))
            found = self._cache[key] = (noise, np.diag(noise).copy(), offset)
            if self._quantised:
                q2 = self.bias_t[channels] ** 2
                assert self._flux_per_wrench is not None
                lsb = self.lsb_t[channels]
                self._bias_maps[key] = (
                    M * M * q2,  # (6 x channels): each channel's q^2 on each axis
                    np.sum(M * M * q2, axis=1),  # untared: q^2 on every channel
                    # (channels x 6): a load's move of each field, in LSBs, times pi sqrt(2)
                    self._flux_per_wrench[channels] * (np.pi * np.sqrt(2.0) / lsb)[:, None],
                )
        return found

    def quantisation(
        self, key: tuple[int, str, bytes], wrench: np.ndarray, known: np.ndarray, tared: bool
    ) -> np.ndarray:
        """The undithered quantisation's variance per axis (6) at ``wrench`` (as published, after
        the tare) for the maps of ``key``: untared sum_c M_kc^2 q_c^2; after a tare each
        channel's bias at the load less the one at the tare's field, whose variance over the
        fields is 2 q^2 (1 - cos(2 pi d / LSB)) for a field moved by d: taken as 2 q^2
        min(1, 2 pi^2 (d / LSB)^2), its small-d form up to its mean, d the field the load
        ``wrench`` less ``known`` (its noise, as the model error's) moves the channel by."""
        found = self._bias_maps.get(key)
        if found is None:
            return np.zeros(6)
        weighted, untared, moves = found
        if not tared:
            return untared
        load = np.copysign(np.maximum(np.abs(wrench) - known, 0.0), wrench)
        if not load.any():
            return np.zeros(6)
        d = moves @ load  # pi sqrt(2) d / LSB a channel
        return 2.0 * (weighted @ np.minimum(1.0, d * d))

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
    ) -> SampleSigma:
        """The sigma of a sample estimated by ``estimator`` from ``chips``; ``wrench``: its
        estimate before the filter (for the model error's load); ``factor``: the filter's
        variance factor (`WrenchFilter.variance_factor`); ``scale``: what the wrench was
        multiplied by after the estimate (the temperature stage's); ``pose``: the nonlinear
        solve's pose and background field (`maps`)."""
        maps = self.maps(version, estimator, chips, tare_samples, pose)
        if maps is None or not np.all(np.isfinite(wrench)):
            return UNKNOWN
        noise, noise_diag, offset = maps
        error = self.nonlinear_error if estimator == "nonlinear" else self.linear_error
        noise_now = factor * noise_diag + np.diag(offset)
        known = NOISE_SIGMAS * np.sqrt(noise_now)
        model = error.variance(wrench, tare_wrench, tared, known)
        if self._quantised:
            model = model + self.quantisation((version, estimator, chips.tobytes()), wrench, known, tared)
        variance = noise_now + model
        sigma = np.sqrt(variance) * scale if scale != 1.0 else np.sqrt(variance)
        # The covariance's parts kept as they are (the cached maps, not copies): only the tip
        # asks for it (`tip_sigma`), so a sample makes no 6 x 6 product.
        return SampleSigma(sigma, noise, offset, model, scale, factor)

    def predicted(
        self, factor: float, tare_samples: int | None, estimator: str = "linear", loaded: bool = False
    ) -> dict[str, Any]:
        """The sigma at rest of the current settings (every chip, no load), and its parts:
        for `status`. ``loaded``: with the undithered quantisation a load brings (its mean over
        the fields, as once a load has moved every channel's field: `quantisation`), which at
        the tare's load is not there: what `accuracy` plans on, as no averaging shrinks it."""
        chips = np.ones(len(self.sigma_t) // 3, dtype=bool)
        maps = self.maps(self._version, estimator, chips, tare_samples)
        if maps is None:
            return {"sigma": None}
        _, noise_diag, offset = maps
        error = self.nonlinear_error if estimator == "nonlinear" else self.linear_error
        tared = tare_samples is not None
        model = error.variance(np.zeros(6), np.zeros(6), tared)
        key = (self._version, estimator, chips.tobytes())
        if loaded and key in self._bias_maps:
            model = model + self._bias_maps[key][1] * (2.0 if tared else 1.0)
        else:
            model = model + self.quantisation(key, np.zeros(6), np.zeros(6), tared)
        sigma = np.sqrt(factor * noise_diag + np.diag(offset) + model)
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
