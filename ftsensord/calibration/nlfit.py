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
"""

from __future__ import annotations

import math
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


def fit_nonlinear(dataset: Dataset) -> NonlinearCalibration:
    """Fit on the dataset's unsaturated "fit" poses (the identifiability checks are the
    linear fit's: run `ftsensord.calibration.fit` first)."""
    rows = (dataset.split == "fit") & ~dataset.saturated.any(axis=1)
    flux, wrench = dataset.flux_t[rows], dataset.wrench[rows]
    if len(flux) < 13:
        raise CalibrationError(f"{len(flux)} usable fit poses: the nonlinear fit needs at least 13")
    # Golden-section search of the gap on the fit residual.
    a, b = GAP_RANGE_M
    phi = (math.sqrt(5) - 1) / 2
    x1, x2 = b - phi * (b - a), a + phi * (b - a)
    f1, f2 = _alternate(flux, wrench, x1), _alternate(flux, wrench, x2)
    for _ in range(GAP_ITERATIONS):
        if f1.fit_rms_residual_t <= f2.fit_rms_residual_t:
            b, x2, f2 = x2, x1, f1
            x1 = b - phi * (b - a)
            f1 = _alternate(flux, wrench, x1)
        else:
            a, x1, f1 = x1, x2, f2
            x2 = a + phi * (b - a)
            f2 = _alternate(flux, wrench, x2)
    return f1 if f1.fit_rms_residual_t <= f2.fit_rms_residual_t else f2


def nonlinear_rmse(cal: NonlinearCalibration, dataset: Dataset) -> np.ndarray:
    """RMSE per axis (N, Nm) of the nonlinear estimate on a dataset."""
    estimator = cal.estimator()
    errors = []
    for b, w in zip(dataset.flux_t, dataset.wrench, strict=True):
        e = estimator.estimate(b)
        errors.append(cal.wrench(e.xi) - w)
    return np.sqrt(np.mean(np.array(errors) ** 2, axis=0))
