"""Calibrating the nonlinear estimator from the same dataset the linear fit uses.

Unknowns: the flux model's per-chip scale and offset (per axis), the magnet gap, the
stiffness K and the zero twist xi0 (w = K (xi - xi0)). The magnet moment is not fitted
on its own: it multiplies every predicted field, which the per-chip scales already do.
Alternating, each step a plain least-squares problem:

1. estimate every fit pose's deflection with the current flux model;
2. fit K and xi0 to the applied wrenches (w = K xi + c);
3. predict each pose from its wrench, xi = K^-1 (w - c), and refit each flux channel's
   scale and offset (b_measured = s b_model(xi) + o: a line per channel).

The gap, which changes the model's shape rather than its scale, is chosen by a short
golden-section search on the fit residual.

A fit is refused (`CalibrationError`, naming the figure) when its gap lands on the
search's bound (the best gap may lie beyond it: the model does not fit this sensor)
or its residual is far above the chips' noise; ``allow_poor_fit`` keeps such a fit
with the reasons in ``warnings``, which the calibration file and report carry. A K
that is not positive definite is refused always: no estimator can use it. Refusing is the default because a nonlinear
model fitted wrong converges at run time to wrong wrenches with no flag: the
estimator's fall-back only catches fits that fail, not a model that is off.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..errors import CalibrationError
from ..model import se3
from ..model.geometry import SensorGeometry
from ..model.nonlinear import FluxModel, NonlinearEstimator
from .dataset import Dataset

ALTERNATIONS = 4
#: The gap is searched in the paper's 6 mm +- 1.5 mm: the silicone layer's thickness
#: varies by casting, not by more.
GAP_RANGE_M = (4.5e-3, 7.5e-3)
GAP_ITERATIONS = 8
#: Gap evaluations a fit makes: two to open the golden section, one per iteration.
GAP_EVALUATIONS = 2 + GAP_ITERATIONS
#: The fit residual (RMS per channel) a right fit stays under: noise alone gives about
#: the mean's standard error, and as-built parts (the tolerances of docs/scenes.md) leave
#: 3 to 4 uT the model cannot absorb (per-magnet placement), so 10 uT, or 10 standard
#: errors where the readings are noisier, separates those from a fit that is off: an
#: unrejected room field leaves 20 uT and more (docs/calibration.md).
RESIDUAL_LIMIT_T = 10e-6
RESIDUAL_NOISE_FACTOR = 10.0


@dataclass(frozen=True)
class FitProgress:
    """Where a nonlinear fit is: ``step`` of ``steps`` gap evaluations done, the gap
    just tried (m) and its fit residual (T, RMS per channel), seconds since the start."""

    step: int
    steps: int
    gap_m: float
    rms_residual_t: float
    elapsed_s: float


@dataclass
class NonlinearCalibration:
    gap_m: float
    scale: np.ndarray  # (n, 3)
    offset_t: np.ndarray  # (n, 3)
    K: np.ndarray  # (6, 6) N/m, Nm/rad
    zero_twist: np.ndarray  # (6,) the deflection read at no load
    fit_rms_residual_t: float
    ring_radius_m: float = 8e-3
    tilt_deg: float = 25.0
    #: Why this fit would have been refused, when kept with ``allow_poor_fit``.
    warnings: tuple[str, ...] = ()

    def geometry(self) -> SensorGeometry:
        return SensorGeometry.ring(radius_m=self.ring_radius_m, tilt_deg=self.tilt_deg, gap_m=self.gap_m)

    def estimator(self) -> NonlinearEstimator:
        g = self.geometry()
        return NonlinearEstimator(FluxModel(g, g.magnet_moment_am2, self.scale.copy(), self.offset_t.copy()), self.K)

    def wrench(self, xi: np.ndarray) -> np.ndarray:
        """w = K (xi - xi0), N and Nm, from an estimated deflection."""
        return self.K @ (xi - self.zero_twist)


def _alternate(flux: np.ndarray, wrench: np.ndarray, gap_m: float) -> NonlinearCalibration:
    g = SensorGeometry.ring(gap_m=gap_m)
    model = FluxModel(g, g.magnet_moment_am2)
    # Start: each channel's offset makes the model match the mean reading at the mean pose (rest).
    model.offset_t = (flux.mean(axis=0) - model.predict(np.eye(4))).reshape(-1, 3)
    estimator = NonlinearEstimator(model, np.eye(6))
    K, c = np.eye(6), np.zeros(6)
    for _ in range(ALTERNATIONS):
        xis = []
        for b in flux:
            e = estimator.estimate(b)
            if not e.converged:
                e = estimator.estimate(b, start=np.eye(4))
            xis.append(e.xi)
        xis_arr = np.array(xis)
        z = np.column_stack([xis_arr, np.ones(len(xis_arr))])
        coef, *_ = np.linalg.lstsq(z, wrench, rcond=None)
        K, c = coef[:6].T, coef[6]
        predicted = np.linalg.solve(K, (wrench - c).T).T  # the pose each wrench should give
        modelled = np.array([model.raw(se3.exp_se3(x)).ravel() for x in predicted])
        # A line per channel: measured = s * modelled + o (a channel that never varies keeps s = 1).
        mm, fm = modelled.mean(axis=0), flux.mean(axis=0)
        var = ((modelled - mm) ** 2).sum(axis=0)
        cov = ((modelled - mm) * (flux - fm)).sum(axis=0)
        s = np.divide(cov, var, out=np.ones_like(var), where=var > 0)
        model.scale = s.reshape(-1, 3)
        model.offset_t = (fm - s * mm).reshape(-1, 3)
    residual = np.array([b - model.predict(se3.exp_se3(x)) for b, x in zip(flux, predicted, strict=True)])
    return NonlinearCalibration(gap_m, model.scale.copy(), model.offset_t.copy(), K, -np.linalg.solve(K, c),
                                float(np.sqrt(np.mean(residual**2))))


def fit_nonlinear(dataset: Dataset, *, progress: Callable[[FitProgress], None] | None = None,
                  allow_poor_fit: bool = False) -> NonlinearCalibration:
    """Fit on the dataset's unsaturated "fit" poses (the identifiability checks are the
    linear fit's: run `ftsensord.calibration.fit` first).

    ``progress`` is called after each of the `GAP_EVALUATIONS` evaluations (each fits
    every pose a few times: about a second per 200 poses). Refuses a fit on the gap's
    search bound or with a residual far above the noise, unless ``allow_poor_fit``:
    then it is kept, the reasons in ``warnings``. Refuses a K not positive definite.
    """
    rows = (dataset.split == "fit") & ~dataset.saturated.any(axis=1)
    flux, wrench = dataset.flux_t[rows], dataset.wrench[rows]
    if len(flux) < 13:
        raise CalibrationError(f"{len(flux)} usable fit poses: the nonlinear fit needs at least 13")
    start = time.monotonic()
    done = 0

    def evaluate(gap_m: float) -> NonlinearCalibration:
        nonlocal done
        result = _alternate(flux, wrench, gap_m)
        done += 1
        if progress is not None:
            progress(FitProgress(done, GAP_EVALUATIONS, gap_m, result.fit_rms_residual_t,
                                 time.monotonic() - start))
        return result

    # Golden-section search of the gap on the fit residual.
    a, b = GAP_RANGE_M
    phi = (math.sqrt(5) - 1) / 2
    x1, x2 = b - phi * (b - a), a + phi * (b - a)
    f1, f2 = evaluate(x1), evaluate(x2)
    for _ in range(GAP_ITERATIONS):
        if f1.fit_rms_residual_t <= f2.fit_rms_residual_t:
            b, x2, f2 = x2, x1, f1
            x1 = b - phi * (b - a)
            f1 = evaluate(x1)
        else:
            a, x1, f1 = x1, x2, f2
            x2 = a + phi * (b - a)
            f2 = evaluate(x2)
    best = f1 if f1.fit_rms_residual_t <= f2.fit_rms_residual_t else f2
    lowest = float(np.linalg.eigvalsh(0.5 * (best.K + best.K.T))[0])
    if not lowest > 0:  # never kept: no estimator can use a stiffness that is none
        raise CalibrationError(f"{dataset.where()}the nonlinear fit is refused: its K is not positive definite "
                               f"(lowest eigenvalue of its symmetric part {lowest:.3g})"
                               + "".join(f"; {p}" for p in _problems(best, (a, b), dataset.flux_sem_t[rows])))
    problems = _problems(best, (a, b), dataset.flux_sem_t[rows])
    if problems and not allow_poor_fit:
        raise CalibrationError(f"{dataset.where()}the nonlinear fit is refused: " + "; ".join(problems)
                               + ". The linear calibration is not affected (calibrate with the nonlinear "
                               "fit off, or allow a poor fit to keep it with these warnings)")
    best.warnings = tuple(problems)
    return best


def _problems(cal: NonlinearCalibration, bracket: tuple[float, float], sem_t: np.ndarray) -> list[str]:
    """What makes a fit untrustworthy, each with its figure (empty: none)."""
    out = []
    low, high = GAP_RANGE_M
    # A bracket that never moved off an end of the range holds the best gap at that end:
    # the residual was still falling there, and the true gap may lie beyond it.
    if bracket[0] == low or bracket[1] == high:
        edge = low if bracket[0] == low else high
        out.append(f"the gap landed on its search bound ({cal.gap_m * 1e3:.3f} mm, bound {edge * 1e3:g} mm of "
                   f"{low * 1e3:g}-{high * 1e3:g} mm): the model does not fit this sensor's flux")
    noise = float(np.median(sem_t)) if sem_t.size else 0.0
    limit = max(RESIDUAL_LIMIT_T, RESIDUAL_NOISE_FACTOR * noise)
    if not cal.fit_rms_residual_t <= limit:
        out.append(f"the fit residual is {cal.fit_rms_residual_t * 1e6:.3g} uT RMS, above the {limit * 1e6:.3g} uT "
                   f"a right fit stays under (noise {noise * 1e6:.3g} uT): a field the model lacks (an "
                   "unrejected room field?) or a chip reading wrong")
    return out


def nonlinear_rmse(cal: NonlinearCalibration, dataset: Dataset) -> np.ndarray:
    """RMSE per axis (N, Nm) of the nonlinear estimate on a dataset."""
    estimator = cal.estimator()
    errors = []
    for b, w in zip(dataset.flux_t, dataset.wrench, strict=True):
        e = estimator.estimate(b)
        errors.append(cal.wrench(e.xi) - w)
    return np.sqrt(np.mean(np.array(errors) ** 2, axis=0))
