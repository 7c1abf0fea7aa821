"""The nonlinear estimator (the paper's future work): the centre-piece pose from all
24 flux values through a magnet field model, then w = K xi.

Forward model: each magnet a point dipole (moment along its axis), the chips where the
pose T puts them, each chip's reading scaled and offset per axis (the free parameters a
calibration fits). Solver: Levenberg-Marquardt on SE(3) with left perturbations
T <- exp(delta) T, analytic Jacobian, warm-started from the previous pose; damped and
step-limited, it reports failure rather than diverge, and the caller falls back to the
linear estimate with a flag.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import se3
from .geometry import SensorGeometry
from .linear import SENSOR_RANGE
from .magnet import MU0_OVER_4PI

#: Largest step per iteration: 1 mm and 0.05 rad. A full-range deflection is about 6 mm
#: and 0.02 rad; steps this size reach it in a few iterations while keeping the dipole
#: model's 1/r^3 curvature from throwing the pose past a magnet.
MAX_STEP_M = 1e-3
MAX_STEP_RAD = 0.05
#: Converged when a step moves the pose less than 1e-8 m and 1e-8 rad: a hundred times
#: below what the chips resolve (a uT in 1.6 mT at 6 mm is about 1 um of motion).
STEP_TOL = 1e-8
#: A fit whose RMS residual exceeds 1 mT is no pose of this sensor (a chip reading wrong,
#: or garbage), however well it converged: the dipole model's own error is about 0.2 mT RMS
#: at the corners of the range (|F| ~70 N with 0.2 Nm) and 7 uT in the middle.
MAX_RESIDUAL_T = 1e-3
#: A warm-started fit left with more than 50 uT RMS may sit in a wrong minimum after a
#: fast change of load: a cold start from the rest pose is tried too and the better fit
#: kept. Right poses stay under 20 uT here for |F| up to 50 N along any direction (the
#: dipole model's error at 6 mm is 29 uT, docs/physics.md); near the corners of the range
#: and on a sensor whose model fits worse, the cold start is paid more often.
RETRY_RESIDUAL_T = 50e-6
#: The ring of 8 identical chips and magnets reads the same after a turn of 45 degrees
#: about its axis: the flux fixes the pose only up to that turn. A deflection whose
#: wrench K xi exceeds 3 times the sensor's range on any axis (the silicone would have
#: torn) is that twin or garbage, never an answer.
PLAUSIBLE_RANGE = 3.0


@dataclass
class FluxModel:
    """Predicted flux (T, chip frames) for a centre-piece pose.

    ``scale`` and ``offset_t`` (n, 3) correct each chip's axes; ``crosstalk`` adds
    every other magnet's field to each chip's.
    """

    geometry: SensorGeometry
    moment_am2: float
    scale: np.ndarray = field(default_factory=lambda: np.ones((8, 3)))
    offset_t: np.ndarray = field(default_factory=lambda: np.zeros((8, 3)))
    crosstalk: bool = True

    def _fields(self, T: np.ndarray, gradient: bool = True
                ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, np.ndarray]:
        """World field B (n, 3), its gradient G (n, 3, 3; None unless asked), chip
        positions p, chip rotations R."""
        g = self.geometry
        R = np.einsum("ij,njk->nik", T[:3, :3], g.chip_R)
        p = g.chip_p @ T[:3, :3].T + T[:3, 3]
        r = p[:, None, :] - g.magnet_p[None, :, :]  # (chip, magnet, 3)
        m = self.moment_am2 * g.magnet_axis[None, :, :]
        if not self.crosstalk:
            own = np.eye(g.n_chips, dtype=bool)
            r, m = r[own][:, None, :], m[0][np.arange(g.n_chips)][:, None, :]
        d2 = np.sum(r * r, axis=-1)[..., None]
        d = np.sqrt(d2)
        rm = np.sum(r * m, axis=-1)[..., None]
        B = MU0_OVER_4PI * (3 * r * rm / d2**2.5 - m / d2**1.5)
        if not gradient:
            return B.sum(axis=1), None, p, R
        # dB/dr of a dipole: k (3 (m r^T + r m^T + (r.m) I) / d^5 - 15 (r.m) r r^T / d^7).
        eye = np.eye(3)
        G = MU0_OVER_4PI * (3 * (m[..., :, None] * r[..., None, :] + r[..., :, None] * m[..., None, :]
                                 + rm[..., None] * eye) / (d[..., None] ** 5)
                            - 15 * rm[..., None] * r[..., :, None] * r[..., None, :] / (d[..., None] ** 7))
        return B.sum(axis=1), G.sum(axis=1), p, R

    def raw(self, T: np.ndarray) -> np.ndarray:
        """The magnets' field at each chip (n, 3), T, chip frames: before scale and offset."""
        B, _, _, R = self._fields(T, gradient=False)
        return np.einsum("nji,nj->ni", R, B)

    def predict(self, T: np.ndarray) -> np.ndarray:
        """Stacked flux (3n,), T, each chip in its own frame."""
        return (self.scale * self.raw(T) + self.offset_t).ravel()

    def predict_and_jacobian(self, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Flux (3n,) and its derivative (3n, 6) for T <- exp([v; w]) T at v = w = 0.

        The chip at p in rotation R reads b = R^T B(p); perturbed, p moves by
        v + w x p and R turns by w, so db/dv = R^T G and db/dw = R^T (hat(B) - G hat(p)).
        """
        B, G, p, R = self._fields(T)
        assert G is not None
        Rt = np.transpose(R, (0, 2, 1))
        J_v = Rt @ G
        J_w = Rt @ (se3.hat(B) - G @ se3.hat(p))
        J = np.concatenate([J_v, J_w], axis=2) * self.scale[:, :, None]
        b = self.scale * np.einsum("nij,nj->ni", Rt, B) + self.offset_t
        return b.ravel(), J.reshape(-1, 6)


@dataclass(frozen=True)
class Estimate:
    xi: np.ndarray  # deflection twist [v; w], m and rad
    pose: np.ndarray  # the centre piece's pose T_0C
    converged: bool
    iterations: int
    rms_residual_t: float  # of the channels used, T


class NonlinearEstimator:
    """Deflection (and so wrench, with ``stiffness``) from flux by Levenberg-Marquardt."""

    def __init__(self, model: FluxModel, stiffness: np.ndarray, *, max_iterations: int = 30):
        self.model = model
        self.stiffness = np.asarray(stiffness, dtype=float)
        self.max_iterations = max_iterations
        self.pose = np.eye(4)  # the warm start: the previous sample's pose

    def estimate(self, b: np.ndarray, usable: np.ndarray | None = None, start: np.ndarray | None = None) -> Estimate:
        """The pose that explains flux ``b`` (3n,) on the usable chips (default all).

        Starts from ``start``; without one, from the previous converged pose, and
        when that fails or fits worse than `RETRY_RESIDUAL_T`, from the rest pose
        too. Never raises on bad data: an estimate that did not converge says so.
        """
        if start is not None:
            return self._solve(b, usable, start)
        warm = self._solve(b, usable, self.pose)
        if warm.converged and warm.rms_residual_t <= RETRY_RESIDUAL_T:
            return warm
        cold = self._solve(b, usable, np.eye(4))
        best = min((warm, cold), key=lambda e: (not e.converged, e.rms_residual_t))
        if best.converged:
            self.pose = best.pose
        return best

    def _solve(self, b: np.ndarray, usable: np.ndarray | None, start: np.ndarray) -> Estimate:
        n = self.model.geometry.n_chips
        channels = np.repeat(np.ones(n, dtype=bool) if usable is None else np.asarray(usable, bool), 3)
        T = np.array(start, dtype=float)
        lam = 1e-3  # Marquardt's damping, relative to the diagonal of J^T J
        cost, done, k = np.inf, False, 0
        if channels.sum() < 6 or not np.all(np.isfinite(b[channels])):
            return Estimate(se3.log_se3(T), T, False, 0, np.inf)
        for k in range(1, self.max_iterations + 1):
            pred, J = self.model.predict_and_jacobian(T)
            r = (b - pred)[channels]
            J = J[channels]
            cost = float(r @ r)
            JtJ, Jtr = J.T @ J, J.T @ r
            while True:
                try:
                    step = np.linalg.solve(JtJ + lam * np.diag(np.diag(JtJ)), Jtr)
                except np.linalg.LinAlgError:
                    return Estimate(se3.log_se3(T), T, False, k, np.sqrt(cost / channels.sum()))
                # 1e-300: a zero step needs no limit (and must not divide by zero).
                scale = min(1.0, MAX_STEP_M / max(float(np.linalg.norm(step[:3])), 1e-300),
                            MAX_STEP_RAD / max(float(np.linalg.norm(step[3:])), 1e-300))
                step = step * scale
                T_new = se3.exp_se3(step) @ T
                r_new = (b - self.model.predict(T_new))[channels]
                if float(r_new @ r_new) <= cost:
                    T, lam = T_new, max(lam / 3, 1e-9)
                    cost = float(r_new @ r_new)
                    break
                lam *= 4
                if lam > 1e8:  # no step lowers the cost: a minimum, or hopeless data
                    done = True
                    break
            if done or (np.linalg.norm(step[:3]) < STEP_TOL and np.linalg.norm(step[3:]) < STEP_TOL):
                break
        rms = np.sqrt(cost / channels.sum())
        xi = se3.log_se3(T)
        plausible = bool(np.all(np.abs(self.stiffness @ xi) <= PLAUSIBLE_RANGE * SENSOR_RANGE))
        converged = bool(np.isfinite(rms) and rms <= MAX_RESIDUAL_T and plausible
                         and (done or k < self.max_iterations))
        if converged:
            self.pose = T
        return Estimate(xi, T, converged, k, float(rms))

    def wrench(self, estimate: Estimate) -> np.ndarray:
        """w = K xi (N, Nm), the stiffness's wrench at the estimated deflection."""
        return self.stiffness @ estimate.xi
