"""Calibrating the nonlinear estimator from the same dataset the linear fit uses.

The flux model (`ftsensord.model.nonlinear.FluxModel`) is fitted to the part, not the
drawing. Unknowns, fitted together by Levenberg-Marquardt on all fit poses:

- each chip's response matrix S_i (3 x 3: gain per axis, cross-axis, and its tilt on
  the part) and offset o_i (72 + 24);
- each magnet's position (24, frame {0}) and moment (8, relative to the D101's): the
  hand-placed magnets and their remanence spread; each a dipole, and for its own chip
  with its octupole too (the estimator's model, `FluxModel.octupole`);
- the compliance C = K^-1 and zero twist d: each pose's deflection is xi = C w + d
  from its applied wrench w (36 + 6);
- per pose, a uniform background field u_k (the room's field turned into {0} by the
  robot): 3 unknowns a pose, eliminated in closed form (variable projection: each
  pose's residual is projected off the 3 flux directions S_i R_i^T that u makes).

A fit is refused (`CalibrationError`, naming the figure) when a magnet lands further
from its drawn place than a hand-made part puts it (`MAGNET_SHIFT_LIMIT_M`: the model
does not fit this sensor) or its residual is far above the chips' noise;
``allow_poor_fit`` keeps such a fit with the reasons in ``warnings``, which the
calibration file and report carry. A K that is not positive definite is refused
always: no estimator can use it. Refusing is the default because a nonlinear model
fitted wrong converges at run time to wrong wrenches with no flag: the estimator's
fall-back only catches fits that fail, not a model that is off.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ftsensord.calibration.dataset import Dataset
from ftsensord.calibration.report import format_rmse
from ftsensord.errors import CalibrationError
from ftsensord.model import se3
from ftsensord.model.geometry import SensorGeometry
from ftsensord.model.linear import SENSOR_RANGE
from ftsensord.model.magnet import MU0_OVER_4PI, dipole_pairs, octupole_field, octupole_ratio
from ftsensord.model.nonlinear import FluxModel, NonlinearEstimator

#: Levenberg-Marquardt iterations of the joint fit: from the start below (the nominal
#: part, K from the estimated deflections) the cost stops falling by 1e-6 of itself
#: within 15-25 on the simulated sensors; a fixed count keeps the progress honest.
FIT_ITERATIONS = 30
#: Nominal gap (m) the fit starts from: the paper's 6 mm; the magnets then move freely.
GAP_M = 6e-3
#: A magnet fitted more than 1 mm from its drawn place is no hand-made part (pockets
#: printed to 0.1 mm, a magnet placed by hand to about as much: docs/design/scenes.md): the
#: fit has gone where the model does not fit this sensor.
MAGNET_SHIFT_LIMIT_M = 1e-3
#: The fit residual (RMS per channel) a right fit stays under: noise alone gives about
#: the mean's standard error (and the dipole model's small error against the magnets'
#: real shape), so 10 uT, or 10 standard errors where the readings are noisier,
#: separates those from a fit that is off (a chip reading wrong, a field that is not
#: uniform across the sensor).
RESIDUAL_LIMIT_T = 10e-6
RESIDUAL_NOISE_FACTOR = 10.0
#: Smallest Marquardt damping (relative to the scaled normal matrix's unit diagonal):
#: the parameters have exact gauges (moving every magnet by t is moving the centre
#: piece by -t; an offset along the background directions is a background field), on
#: which only the damping holds the step; 1e-6 keeps it finite without slowing the rest.
MIN_DAMPING = 1e-6
#: A kept fit whose residual is above this many times the readings' noise (a mean's
#: standard error) departs from the model in a way its parameters cannot absorb: the
#: default scene's as-built sensor1 leaves 1.2x (0.36 against 0.29 uT); silicone 30 %
#: stiffer at range leaves 2.5x (benchmarks/robustness/pathological.py).
DEPARTURE_NOISE_FACTOR = 2.0
#: Its error on the heaviest poses growing more than this many times its error on the
#: lightest names the silicone's stiffening: the model's compliance is linear, so its
#: error grows with the load's cube where the silicone stiffens (3x from 50 to 200 g
#: with 30 % at range), and not at all where noise dominates (0.9-1.2x as built).
GROWTH_WARN = 2.0


@dataclass(frozen=True)
class FitProgress:
    """Where a nonlinear fit is: ``step`` of ``steps`` iterations done, the mean
    magnet gap (m) and the fit residual (T, RMS per channel), seconds since the start."""

    step: int
    steps: int
    gap_m: float
    rms_residual_t: float
    elapsed_s: float


@dataclass
class NonlinearCalibration:
    """A fitted flux model and stiffness: w = K (xi - zero_twist).

    ``scale`` is each chip's response, per axis (n, 3) or a full matrix (n, 3, 3);
    ``magnet_p_m`` (n, 3, frame {0}) and ``magnet_strength`` (n,) place the magnets
    and scale their moments as fitted (None: as drawn, with ``gap_m``)."""

    gap_m: float
    scale: np.ndarray  # (n, 3) or (n, 3, 3)
    offset_t: np.ndarray  # (n, 3)
    K: np.ndarray  # (6, 6) N/m, Nm/rad
    zero_twist: np.ndarray  # (6,) the deflection read at no load
    fit_rms_residual_t: float
    ring_radius_m: float = 8e-3
    tilt_deg: float = 25.0
    #: Why this fit would have been refused, when kept with ``allow_poor_fit``.
    warnings: tuple[str, ...] = ()
    magnet_p_m: np.ndarray | None = None
    magnet_strength: np.ndarray | None = None
    #: Each chip's own magnet with its octupole (`FluxModel.octupole`); files written
    #: before it (no ``field_model``) were fitted with dipoles alone.
    octupole: bool = True

    def geometry(self) -> SensorGeometry:
        g = SensorGeometry.ring(radius_m=self.ring_radius_m, tilt_deg=self.tilt_deg, gap_m=self.gap_m)
        if self.magnet_p_m is None and self.magnet_strength is None:
            return g
        return SensorGeometry(
            g.chip_R,
            g.chip_p,
            g.magnet_p if self.magnet_p_m is None else self.magnet_p_m,
            g.magnet_axis,
            g.magnet_radius_m,
            g.magnet_length_m,
            g.magnet_br_t,
            self.magnet_strength,
        )

    def estimator(self, background: bool = True) -> NonlinearEstimator:
        g = self.geometry()
        return NonlinearEstimator(
            FluxModel(
                g, g.magnet_moment_am2, self.scale.copy(), self.offset_t.copy(), octupole=self.octupole
            ),
            self.K,
            background=background,
            zero_twist=self.zero_twist,
        )

    def wrench(self, xi: np.ndarray) -> np.ndarray:
        """w = K (xi - xi0), N and Nm, from an estimated deflection."""
        return self.K @ (xi - self.zero_twist)

    def document(self) -> dict[str, Any]:
        """The calibration file's ``nonlinear`` section (docs/guide/calibration.md)."""
        doc: dict[str, Any] = {
            "gap_m": self.gap_m,
            "ring_radius_m": self.ring_radius_m,
            "tilt_deg": self.tilt_deg,
            "scale": np.asarray(self.scale).tolist(),
            "offset_t": self.offset_t.tolist(),
            "K": self.K.tolist(),
            "zero_twist": self.zero_twist.tolist(),
            "fit_rms_residual_t": self.fit_rms_residual_t,
            "field_model": "dipole+octupole" if self.octupole else "dipole",
        }
        if self.magnet_p_m is not None:
            doc["magnet_p_m"] = self.magnet_p_m.tolist()
        if self.magnet_strength is not None:
            doc["magnet_strength"] = self.magnet_strength.tolist()
        if self.warnings:  # a fit kept against its refusal: the reasons travel with it
            doc["warnings"] = list(self.warnings)
        return doc


class _Problem:
    """The joint fit's residual and Jacobian over all fit poses (see the module's doc)."""

    def __init__(self, flux: np.ndarray, wrench: np.ndarray, geometry: SensorGeometry, octupole: bool = True):
        self.flux, self.wrench, self.g, self.octupole = flux, wrench, geometry, octupole
        self.n = geometry.n_chips
        self.moment = geometry.magnet_moment_am2
        n = self.n
        # Parameter layout: S (9n), o (3n), magnet positions (3n), strengths (n), C (36), d (6).
        sizes = {"S": 9 * n, "o": 3 * n, "mp": 3 * n, "s": n, "C": 36, "d": 6}
        self.slices, at = {}, 0
        for name, size in sizes.items():
            self.slices[name] = slice(at, at + size)
            at += size
        self.size = at

    def unpack(self, theta: np.ndarray) -> dict[str, np.ndarray]:
        n = self.n
        shapes = {"S": (n, 3, 3), "o": (n, 3), "mp": (n, 3), "s": (n,), "C": (6, 6), "d": (6,)}
        return {k: theta[self.slices[k]].reshape(shapes[k]) for k in shapes}

    def pack(self, S, o, mp, s, C, d) -> np.ndarray:
        return np.concatenate([np.ravel(S), np.ravel(o), np.ravel(mp), np.ravel(s), np.ravel(C), np.ravel(d)])

    def evaluate(
        self, theta: np.ndarray, jacobian: bool = True
    ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        """Residual (N*3n,) projected off each pose's background directions, its
        Jacobian (N*3n, size) (Kaufman's: the directions' own derivative left out, as
        variable projection allows), and each pose's background field (N, 3; T, {0})."""
        P = self.unpack(theta)
        g, n = self.g, self.n
        xis = self.wrench @ P["C"].T + P["d"]
        Ts = np.array([se3.exp_se3(x) for x in xis])
        R = np.einsum("kij,njl->knil", Ts[:, :3, :3], g.chip_R)  # (N, n, 3, 3) chip rotations
        p = np.einsum("kij,nj->kni", Ts[:, :3, :3], g.chip_p) + Ts[:, None, :3, 3]
        r = p[:, :, None, :] - P["mp"][None, None, :, :]  # (N, chip, magnet, 3)
        m = self.moment * P["s"][:, None] * g.magnet_axis
        Bij, Gij = dipole_pairs(r, np.broadcast_to(m, r.shape), jacobian)
        if self.octupole:  # each chip's own magnet's octupole (FluxModel's), on the diagonal pairs
            own = np.arange(n)
            q = MU0_OVER_4PI * self.moment * P["s"] * octupole_ratio(g.magnet_radius_m, g.magnet_length_m)
            B3, G3 = octupole_field(r[:, own, own], g.magnet_axis, np.broadcast_to(q, r.shape[:2]), jacobian)
            Bij[:, own, own] += B3
            if Gij is not None:
                Gij[:, own, own] += G3
        B = Bij.sum(axis=2)
        SRt = P["S"][None] @ np.swapaxes(R, -1, -2)  # (N, n, 3, 3)
        raw = np.einsum("knji,knj->kni", R, B)  # the field in each chip's frame
        pred = np.einsum("nij,knj->kni", P["S"], raw) + P["o"]
        N = len(xis)
        U = SRt.reshape(N, n, 3, 3).reshape(N, 3 * n, 3)
        Q, Rq = np.linalg.qr(U)  # (N, 3n, 3) orthonormal background directions per pose
        r_full = self.flux - pred.reshape(N, -1)
        coef = np.einsum("kci,kc->ki", Q, r_full)
        resid = r_full - np.einsum("kci,ki->kc", Q, coef)
        u = np.linalg.solve(Rq, coef[..., None])[..., 0]  # each pose's best background field (T, {0})
        if not jacobian:
            return resid.ravel(), None, u
        assert Gij is not None
        G = Gij.sum(axis=2)
        # The model with each pose's background field in: S R^T (B + u). Its derivative,
        # projected, is variable projection's (Kaufman's: only the term that vanishes
        # with the residual is left out).
        B = B + u[:, None, :]
        raw_u = np.einsum("knji,knj->kni", R, B)
        J = np.zeros((N, n, 3, self.size))
        eye_n = np.eye(n)
        # S_i[a, b] multiplies raw_i[b] in output a of chip i.
        JS = np.einsum("kib,ij,ac->kiajcb", raw_u, eye_n, np.eye(3))  # (N, n, 3, n, 3, 3)
        J[..., self.slices["S"]] = JS.reshape(N, n, 3, -1)
        J[..., self.slices["o"]] = np.einsum("ij,ac->iajc", eye_n, np.eye(3)).reshape(n, 3, -1)[None]
        # A magnet moved by dm moves r by -dm: -S R^T G_ij per pair.
        J[..., self.slices["mp"]] = -np.einsum("kiab,kijbc->kiajc", SRt, Gij).reshape(N, n, 3, -1)
        safe = np.where(P["s"] != 0, P["s"], 1.0)  # the field is linear in each magnet's moment
        J[..., self.slices["s"]] = np.einsum("kiab,kijb->kiaj", SRt, Bij / safe[None, None, :, None])
        hB, hp = se3.hat(B), se3.hat(p)
        Jpose = np.concatenate([SRt @ G, SRt @ (hB - G @ hp)], axis=3)  # (N, n, 3, 6), left perturbation
        # d exp(xi)/d xi is the left perturbation times SE(3)'s left Jacobian, I + ad(xi)/2 to
        # first order (ad = [[hat w, hat v], [0, hat w]]): its second-order term is
        # |xi|^2/6, under 1e-5 at full range, while leaving out ad(xi)/2 errs by 20 %.
        ad = np.zeros((N, 6, 6))
        ad[:, :3, :3] = ad[:, 3:, 3:] = se3.hat(xis[:, 3:])
        ad[:, :3, 3:] = se3.hat(xis[:, :3])
        Jpose = Jpose @ (np.eye(6) + 0.5 * ad)[:, None]
        J[..., self.slices["C"]] = np.einsum("kiae,kf->kiaef", Jpose, self.wrench).reshape(N, n, 3, -1)
        J[..., self.slices["d"]] = Jpose
        Jf = J.reshape(N, 3 * n, self.size)
        # The model's derivative enters the residual with a minus sign: r = b - f.
        Jr = -(Jf - np.einsum("kci,kip->kcp", Q, np.einsum("kci,kcp->kip", Q, Jf)))
        return resid.ravel(), Jr.reshape(N * 3 * n, self.size), u


def _start(flux: np.ndarray, wrench: np.ndarray, problem: _Problem) -> np.ndarray:
    """The nominal part; K and the zero from the deflections it estimates (background
    field estimated too), the offsets matching the mean reading at the mean pose."""
    g = problem.g
    model = FluxModel(g, g.magnet_moment_am2, octupole=problem.octupole)
    model.offset_t = (flux.mean(axis=0) - model.predict(np.eye(4))).reshape(-1, 3)
    estimator = NonlinearEstimator(model, np.eye(6) * 1e9)  # no plausibility limit while K is unknown
    xis = np.array([estimator.estimate(b).xi for b in flux])
    z = np.column_stack([wrench, np.ones(len(wrench))])
    coef, *_ = np.linalg.lstsq(z, xis, rcond=None)  # xi = C w + d
    n = g.n_chips
    return problem.pack(
        np.tile(np.eye(3), (n, 1, 1)), model.offset_t, g.magnet_p, np.ones(n), coef[:6].T, coef[6]
    )


def fit_nonlinear(
    dataset: Dataset,
    *,
    progress: Callable[[FitProgress], None] | None = None,
    allow_poor_fit: bool = False,
    octupole: bool = True,
) -> NonlinearCalibration:
    """Fit on the dataset's unsaturated "fit" poses (the identifiability checks are the
    linear fit's: run `ftsensord.calibration.fit` first).

    ``progress`` is called after each of the `FIT_ITERATIONS` iterations. Refuses a
    fit with a magnet beyond `MAGNET_SHIFT_LIMIT_M` of its drawn place or a residual
    far above the noise, unless ``allow_poor_fit``: then it is kept, the reasons in
    ``warnings``. Refuses a K not positive definite. ``octupole=False`` fits the dipole
    model alone (the earlier one: benchmarks/accuracy/accuracy.py measures what the octupole buys).
    """
    rows = (dataset.split == "fit") & ~dataset.saturated.any(axis=1)
    flux, wrench = dataset.flux_t[rows], dataset.wrench[rows]
    if len(flux) < 13:
        raise CalibrationError(f"{len(flux)} usable fit poses: the nonlinear fit needs at least 13")
    begin = time.monotonic()
    geometry = SensorGeometry.ring(gap_m=GAP_M)
    problem = _Problem(flux, wrench, geometry, octupole)
    theta = _start(flux, wrench, problem)
    r, J, _ = problem.evaluate(theta)
    assert J is not None
    cost, lam = float(r @ r), 1e-3
    for step in range(1, FIT_ITERATIONS + 1):
        JtJ, Jtr = J.T @ J, J.T @ r
        d = np.sqrt(np.diag(JtJ))
        d = np.where(d > 0, d, 1.0)  # a parameter nothing depends on: unit scale, the damping holds it
        A, gvec = JtJ / np.outer(d, d), Jtr / d
        while True:
            delta = -np.linalg.solve(A + lam * np.eye(problem.size), gvec) / d
            r_new, J_new, _ = problem.evaluate(theta + delta)
            cost_new = float(r_new @ r_new)
            if np.isfinite(cost_new) and cost_new <= cost:
                theta, r, J, cost, lam = theta + delta, r_new, J_new, cost_new, max(lam / 3, MIN_DAMPING)
                break
            lam *= 4
            if lam > 1e8:  # no step lowers the cost: a minimum
                break
        assert J is not None
        if progress is not None:
            P = problem.unpack(theta)
            progress(
                FitProgress(
                    step,
                    FIT_ITERATIONS,
                    _mean_gap(geometry, P["mp"]),
                    float(np.sqrt(cost / r.size)),
                    time.monotonic() - begin,
                )
            )
    P = problem.unpack(theta)
    K = np.linalg.inv(P["C"])
    cal = NonlinearCalibration(
        GAP_M,
        P["S"].copy(),
        P["o"].copy(),
        K,
        P["d"].copy(),
        float(np.sqrt(cost / r.size)),
        magnet_p_m=P["mp"].copy(),
        magnet_strength=P["s"].copy(),
        octupole=octupole,
    )
    problems = _problems(cal, geometry, dataset.flux_sem_t[rows])
    lowest = float(np.linalg.eigvalsh(0.5 * (K + K.T))[0])
    if not lowest > 0:  # never kept: no estimator can use a stiffness that is none
        raise CalibrationError(
            f"{dataset.where()}the nonlinear fit is refused: its K is not positive definite "
            f"(lowest eigenvalue of its symmetric part {lowest:.3g})" + "".join(f"; {p}" for p in problems)
        )
    if problems and not allow_poor_fit:
        raise CalibrationError(
            f"{dataset.where()}the nonlinear fit is refused: "
            + "; ".join(problems)
            + ". The linear calibration is not affected (calibrate with the nonlinear "
            "fit off, or allow a poor fit to keep it with these warnings)"
        )
    cal.warnings = tuple(problems) + departure(cal, dataset.select(rows))
    return cal


def departure(cal: NonlinearCalibration, fitted: Dataset) -> tuple[str, ...]:
    """What the fitted model cannot absorb, judged on the poses it was fitted on: its
    residual against the noise, its fall-backs, its error growing with the load; each
    warning says what accuracy to expect (its error on those poses, RMS per axis)."""
    estimator = cal.estimator()
    estimates = [estimator.estimate(b) for b in fitted.flux_t]
    fell = sum(not e.converged for e in estimates)
    noise = float(np.median(fitted.flux_sem_t)) if fitted.flux_sem_t.size else 0.0
    ratio = cal.fit_rms_residual_t / noise if noise > 0 else 0.0
    if fell == 0 and ratio <= DEPARTURE_NOISE_FACTOR:
        return ()
    ok = np.array([e.converged for e in estimates])
    error = np.array([cal.wrench(e.xi) for e, c in zip(estimates, ok) if c]) - fitted.wrench[ok]
    scaled = np.linalg.norm(error / SENSOR_RANGE, axis=1)
    masses = fitted.mass_kg[ok]
    light, heavy = masses == masses.min(), masses == masses.max()
    growth = float(np.sqrt(np.mean(scaled[heavy] ** 2) / np.mean(scaled[light] ** 2))) if light.any() else 1.0
    why = (
        f"its error grows {growth:.2g}x from the {masses.min():g} kg to the {masses.max():g} kg poses: the "
        "silicone stiffens with load, which its linear compliance cannot follow"
        if growth > GROWTH_WARN
        else "silicone that stiffens, magnets tilted, or a field not uniform across the sensor"
    )
    force, torque = (np.linalg.norm(fitted.wrench[:, a : a + 3], axis=1).max() for a in (0, 3))
    return (
        f"the nonlinear model departs from this part: it leaves {cal.fit_rms_residual_t * 1e6:.3g} uT RMS on "
        f"its own poses, {ratio:.2g}x the readings' noise ({noise * 1e6:.3g} uT), and falls back on {fell} of "
        f"{len(estimates)} of them; {why}. Expect at least its error on those poses, "
        f"{format_rmse(np.sqrt(np.mean(error**2, axis=0)).tolist())} RMS, and more beyond the calibration's "
        f"largest load (|F| {force:.3g} N, |M| {torque:.3g} Nm)",
    )


def _mean_gap(geometry: SensorGeometry, magnet_p: np.ndarray) -> float:
    """The magnets' mean distance from their chips along the chips' axes (m)."""
    return float(np.mean(np.einsum("ni,ni->n", magnet_p - geometry.chip_p, geometry.chip_R[:, :, 2])))


def _problems(cal: NonlinearCalibration, drawn: SensorGeometry, sem_t: np.ndarray) -> list[str]:
    """What makes a fit untrustworthy, each with its figure (empty: none)."""
    out = []
    assert cal.magnet_p_m is not None
    shift = np.linalg.norm(cal.magnet_p_m - drawn.magnet_p, axis=1)
    worst = int(np.argmax(shift))
    if shift[worst] > MAGNET_SHIFT_LIMIT_M:
        out.append(
            f"magnet {worst + 1} was fitted {shift[worst] * 1e3:.2f} mm from its drawn place (a hand-made "
            f"part is within {MAGNET_SHIFT_LIMIT_M * 1e3:g} mm): the model does not fit this sensor's flux"
        )
    noise = float(np.median(sem_t)) if sem_t.size else 0.0
    limit = max(RESIDUAL_LIMIT_T, RESIDUAL_NOISE_FACTOR * noise)
    if not cal.fit_rms_residual_t <= limit:
        out.append(
            f"the fit residual is {cal.fit_rms_residual_t * 1e6:.3g} uT RMS, above the {limit * 1e6:.3g} uT "
            f"a right fit stays under (noise {noise * 1e6:.3g} uT): a field the model lacks (one not "
            "uniform across the sensor?) or a chip reading wrong"
        )
    return out


def nonlinear_errors(cal: NonlinearCalibration, dataset: Dataset) -> np.ndarray:
    """The nonlinear estimate's error (poses x 6, N and Nm) on a dataset."""
    estimator = cal.estimator()
    errors = []
    for b, w in zip(dataset.flux_t, dataset.wrench, strict=True):
        e = estimator.estimate(b)
        errors.append(cal.wrench(e.xi) - w)
    return np.array(errors).reshape(-1, 6)


def nonlinear_rmse(cal: NonlinearCalibration, dataset: Dataset) -> np.ndarray:
    """RMSE per axis (N, Nm) of the nonlinear estimate on a dataset."""
    return np.sqrt(np.mean(nonlinear_errors(cal, dataset) ** 2, axis=0))
