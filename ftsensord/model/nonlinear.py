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

import math
from dataclasses import dataclass, field, replace

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
#: The background field is estimated with a Gaussian prior, zero mean (the room as at
#: calibration and tare) and 50 uT per axis (the Earth's field is 25-65 uT anywhere, so
#: turning the tool changes it by at most twice that), weighed against 1 uT of flux noise
#: per channel. Why a prior: the ring is symmetric about z, so an axial push (Fz) and a
#: uniform field along z both change each chip's flux only in its radial-axial plane; at
#: Fz near 12 N the radial change's slope in z passes through zero and the two cannot be
#: told apart (an exact twin beyond it: 20 N reads as 4.5 N in a 1.5 mT field,
#: tests/test_nonlinear.py). There the prior keeps u near zero: the estimate is then as
#: good as one without a background term, and elsewhere the data outweigh the prior.
BACKGROUND_PRIOR_T = 50e-6
#: Marquardt's starting damping from the previous sample's pose: that pose is a sample
#: (10 ms) away, where the model is all but linear, so the step starts as Gauss-Newton's
#: and converges in two iterations where 1e-3 damps the first step enough to need a
#: third; a step that raises the cost is still refused and the damping raised (x4).
WARM_DAMPING = 1e-6
#: A background field above 0.5 mT (10 times the Earth's) is no room's: the fit sits
#: on the axial twin above (1.5 mT), or the flux is garbage. Not an answer.
BACKGROUND_LIMIT_T = 0.5e-3
BACKGROUND_NOISE_T = 1e-6


_EYE3 = np.eye(3)


def dipole_pairs(r: np.ndarray, m: np.ndarray, gradient: bool = True
                 ) -> tuple[np.ndarray, np.ndarray | None]:
    """Field (..., 3) and its gradient dB/dr (..., 3, 3; None unless asked) of point
    dipoles of moment ``m`` (A m^2) at offsets ``r`` (m) from them, T and T/m, per pair:
    the sums over magnets are the caller's (the calibration needs them one by one)."""
    B, parts = _dipole_field(r, m)
    return B, (_dipole_gradient(r, m, *parts) if gradient else None)


def _dipole_field(r: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
    """`dipole_pairs`'s field, and what its gradient reuses (d^2, r.m, k / d^5)."""
    # As few numpy operations as the formulas allow: at 8 x 8 pairs each costs more in
    # call overhead than in arithmetic, and the estimator runs this twice an iteration.
    d2 = np.einsum("...i,...i->...", r, r)[..., None]
    rm = np.einsum("...i,...i->...", r, m)[..., None]
    k_d5 = MU0_OVER_4PI / (d2 * d2 * np.sqrt(d2))
    return k_d5 * (3 * rm * r - d2 * m), (d2, rm, k_d5)


def _dipole_gradient(r: np.ndarray, m: np.ndarray, d2: np.ndarray, rm: np.ndarray, k_d5: np.ndarray) -> np.ndarray:
    """dB/dr of a dipole: k (3 (m r^T + r m^T + (r.m) I) / d^5 - 15 (r.m) r r^T / d^7)."""
    mr = m[..., :, None] * r[..., None, :]
    outer = mr + np.swapaxes(mr, -1, -2) + rm[..., None] * _EYE3
    return k_d5[..., None] * (3 * outer - (15 * rm / d2)[..., None] * (r[..., :, None] * r[..., None, :]))


@dataclass
class FluxModel:
    """Predicted flux (T, chip frames) for a centre-piece pose and a background field.

    Chip i reads ``S_i R_i^T (B(p_i) + u) + o_i``: B the magnets' field (each a point
    dipole at ``geometry.magnet_p``, moment ``moment_am2`` times ``geometry.strengths``,
    along its axis; every other magnet's field too with ``crosstalk``), R_i and p_i the
    chip's rotation and position (moved by the pose), u a uniform background field in
    {0} (the room's; T). ``scale`` is S: per axis (n, 3) or a full response matrix per
    chip (n, 3, 3), which also absorbs a chip's tilt on the part; ``offset_t`` (n, 3) is o.
    """

    geometry: SensorGeometry
    moment_am2: float
    scale: np.ndarray = field(default_factory=lambda: np.ones((8, 3)))
    offset_t: np.ndarray = field(default_factory=lambda: np.zeros((8, 3)))
    crosstalk: bool = True

    @property
    def response(self) -> np.ndarray:
        """S as a matrix per chip (n, 3, 3); kept while ``scale`` is the same array."""
        cached = self.__dict__.get("_response")
        if cached is not None and cached[0] is self.scale and np.array_equal(cached[1], self.scale):
            return cached[2]  # the same scale, not changed in place since
        s = np.asarray(self.scale, dtype=float)
        response = s if s.ndim == 3 else s[:, :, None] * np.eye(3)
        self.__dict__["_response"] = (self.scale, s.copy(), response)
        return response

    @property
    def _response_chip(self) -> np.ndarray:
        """S R_chip^T (n, 3, 3), fixed while S and the geometry are: a pose's S R^T is
        this times R_T^T, one product where two were."""
        response = self.response
        cached = self.__dict__.get("_response_chip_cache")
        if cached is not None and cached[0] is response and cached[1] is self.geometry.chip_R:
            return cached[2]
        value = response @ np.transpose(self.geometry.chip_R, (0, 2, 1))
        self.__dict__["_response_chip_cache"] = (response, self.geometry.chip_R, value)
        return value

    def _fields(self, T: np.ndarray, gradient: bool = True
                ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, np.ndarray]:
        """World field B (n, 3), its gradient G (n, 3, 3; None unless asked), chip
        positions p, chip rotations R."""
        # The estimator asks the field at a pose (is the step better?) and then, at the
        # same pose, its gradient too: the field's part is kept for that second call.
        last = self.__dict__.get("_last_field")
        key = (self.crosstalk, self.moment_am2, id(self.geometry))  # what else the field depends on
        if last is not None and last[0] is T and last[2] == key and np.array_equal(last[1], T):
            _, _, _, B_sum, p, R, r, m, parts = last
        else:
            g = self.geometry
            R = np.einsum("ij,njk->nik", T[:3, :3], g.chip_R)
            p = g.chip_p @ T[:3, :3].T + T[:3, 3]
            r = p[:, None, :] - g.magnet_p[None, :, :]  # (chip, magnet, 3)
            m = (self.moment_am2 * g.strengths[:, None] * g.magnet_axis)[None, :, :]
            if not self.crosstalk:
                own = np.arange(g.n_chips)
                r, m = r[own, own][:, None, :], m[0][own][:, None, :]
            B, parts = _dipole_field(r, m)  # m broadcasts over the chips
            B_sum = B.sum(axis=1)
            self.__dict__["_last_field"] = (T, T.copy(), key, B_sum, p, R, r, m, parts)
        G = _dipole_gradient(r, m, *parts).sum(axis=1) if gradient else None
        return B_sum, G, p, R

    def raw(self, T: np.ndarray) -> np.ndarray:
        """The magnets' field at each chip (n, 3), T, chip frames: before scale and offset."""
        B, _, _, R = self._fields(T, gradient=False)
        return np.einsum("nji,nj->ni", R, B)

    def predict(self, T: np.ndarray, u: np.ndarray | None = None) -> np.ndarray:
        """Stacked flux (3n,), T, each chip in its own frame; ``u`` the background field
        in {0} (T; default none)."""
        B, _, _, _ = self._fields(T, gradient=False)
        if u is not None:
            B = B + u
        SRt = self._response_chip @ T[:3, :3].T  # S R^T, R = R_T R_chip
        return (np.einsum("nij,nj->ni", SRt, B) + self.offset_t).ravel()

    def predict_and_jacobian(self, T: np.ndarray, u: np.ndarray | None = None,
                             background: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Flux (3n,) and its derivative (3n, 6) for T <- exp([v; w]) T at v = w = 0;
        with ``background``, (3n, 9): the last 3 columns d/du, u the background field.

        The chip at p in rotation R reads b = S R^T (B(p) + u); perturbed, p moves by
        v + w x p and R turns by w, so db/dv = S R^T G, db/dw = S R^T (hat(B + u) - G hat(p))
        and db/du = S R^T.
        """
        B, G, p, _ = self._fields(T)
        assert G is not None
        if u is not None:
            B = B + u
        SRt = self._response_chip @ T[:3, :3].T  # S R^T, R = R_T R_chip
        J_v = SRt @ G
        J_w = SRt @ (se3.hat(B) - G @ se3.hat(p))
        blocks = [J_v, J_w, SRt] if background else [J_v, J_w]
        J = np.concatenate(blocks, axis=2)
        b = np.einsum("nij,nj->ni", SRt, B) + self.offset_t
        return b.ravel(), J.reshape(-1, J.shape[2])

    def background_directions(self, T: np.ndarray | None = None) -> np.ndarray:
        """U (3n, 3): the flux a unit background field along x, y, z of {0} adds (T/T)."""
        R = self.geometry.chip_R if T is None else np.einsum("ij,njk->nik", T[:3, :3], self.geometry.chip_R)
        return (self.response @ np.transpose(R, (0, 2, 1))).reshape(-1, 3)


@dataclass(frozen=True)
class Estimate:
    xi: np.ndarray  # deflection twist [v; w], m and rad
    pose: np.ndarray  # the centre piece's pose T_0C
    converged: bool
    iterations: int
    rms_residual_t: float  # of the channels used, T
    #: The uniform background field estimated beside the pose (T, frame {0}); zeros
    #: when the estimator does not estimate one.
    background_t: np.ndarray = field(default_factory=lambda: np.zeros(3))


class NonlinearEstimator:
    """Deflection (and so wrench, with ``stiffness``) from flux by Levenberg-Marquardt.

    With ``background`` (the default) a uniform field u (3 unknowns, frame {0}) is
    estimated with the 6 of the pose, 9 from the 24 readings: the room's field, which
    turns in the sensor's frame as the tool turns, then moves u and not the wrench.
    """

    def __init__(self, model: FluxModel, stiffness: np.ndarray, *, max_iterations: int = 30,
                 background: bool = True, zero_twist: np.ndarray | None = None):
        self.model = model
        self.stiffness = np.asarray(stiffness, dtype=float)
        #: The deflection read at no load (m, rad): the plausibility test judges the wrench
        #: K (xi - zero_twist), the one published, not K xi.
        self.zero_twist = np.zeros(6) if zero_twist is None else np.asarray(zero_twist, dtype=float)
        self.max_iterations = max_iterations
        self.background = background
        self.pose = np.eye(4)  # the warm start: the previous sample's pose
        self.background_t = np.zeros(3)  # and its background field

    @property
    def unknowns(self) -> int:
        return 9 if self.background else 6

    def estimate(self, b: np.ndarray, usable: np.ndarray | None = None, start: np.ndarray | None = None) -> Estimate:
        """The pose that explains flux ``b`` (3n,) on the usable chips (default all).

        Starts from ``start`` (the background field from zero); without one, from the
        previous converged pose and field, and when that fails or fits worse than
        `RETRY_RESIDUAL_T`, from the rest pose too. Never raises on bad data: an
        estimate that did not converge says so.
        """
        if start is not None:
            return self._cold(b, usable, start)
        warm = self._solve(b, usable, self.pose, self.background_t, self.background, WARM_DAMPING)
        if warm.converged and warm.rms_residual_t <= RETRY_RESIDUAL_T:
            return warm
        cold = self._cold(b, usable, np.eye(4))
        best = min((warm, cold), key=lambda e: (not e.converged, e.rms_residual_t))
        if best.converged:
            self.pose, self.background_t = best.pose, best.background_t
        return best

    def _cold(self, b: np.ndarray, usable: np.ndarray | None, start: np.ndarray) -> Estimate:
        """From ``start`` with no background field: the pose alone first, then with the
        field. Both at once from far away can run to the axial twin (`BACKGROUND_PRIOR_T`);
        the pose alone cannot, and from its answer the field is a small correction."""
        if not self.background:
            return self._solve(b, usable, start, np.zeros(3), False)
        first = self._solve(b, usable, start, np.zeros(3), False)
        if not np.all(np.isfinite(first.pose)) or first.iterations == 0:
            return first
        second = self._solve(b, usable, first.pose, np.zeros(3), True)
        return replace(second, iterations=first.iterations + second.iterations)

    def _solve(self, b: np.ndarray, usable: np.ndarray | None, start: np.ndarray, u0: np.ndarray,
               background: bool, damping: float = 1e-3) -> Estimate:
        n = self.model.geometry.n_chips
        channels = np.repeat(np.ones(n, dtype=bool) if usable is None else np.asarray(usable, bool), 3)
        T = np.array(start, dtype=float)
        u = np.array(u0, dtype=float) if background else None
        lam = damping  # Marquardt's damping, relative to the diagonal of J^T J
        cost, done, k = np.inf, False, 0
        # The unknowns need as many channels: 6 for the pose, 9 with the background field.
        if channels.sum() < (9 if background else 6) or not np.all(np.isfinite(b[channels])):
            return Estimate(se3.log_se3(T), T, False, 0, np.inf)
        used = int(channels.sum())
        # Every chip usable (the usual case): a slice, which copies nothing.
        channels = slice(None) if used == channels.size else channels  # type: ignore[assignment]
        for k in range(1, self.max_iterations + 1):
            pred, J = self.model.predict_and_jacobian(T, u, background)
            r = (b - pred)[channels]
            J = J[channels]
            cost = float(r @ r) + _prior(u)
            JtJ, Jtr = J.T @ J, J.T @ r
            if u is not None:  # the prior's rows: (noise / prior) (u + du) = 0
                JtJ[6:, 6:] += PRIOR_WEIGHT * np.eye(3)
                Jtr[6:] -= PRIOR_WEIGHT * u
            while True:
                try:
                    damped = JtJ.copy()
                    damped.flat[::damped.shape[0] + 1] *= 1 + lam  # JtJ + lam diag(JtJ)
                    step = np.linalg.solve(damped, Jtr)
                except np.linalg.LinAlgError:
                    return Estimate(se3.log_se3(T), T, False, k, np.sqrt(cost / used), _field(u))
                # 1e-300: a zero step needs no limit (and must not divide by zero). The
                # background field enters linearly: its step needs no limit of its own.
                v, w = step[:6].tolist()[:3], step[:6].tolist()[3:]
                scale = min(1.0, MAX_STEP_M / max(math.hypot(*v), 1e-300),
                            MAX_STEP_RAD / max(math.hypot(*w), 1e-300))
                step = step * scale
                T_new = _exp_se3(step[:6]) @ T
                u_new = None if u is None else u + step[6:]
                r_new = (b - self.model.predict(T_new, u_new))[channels]
                if float(r_new @ r_new) + _prior(u_new) <= cost:
                    T, u, lam = T_new, u_new, max(lam / 3, 1e-9)
                    cost = float(r_new @ r_new) + _prior(u_new)
                    break
                lam *= 4
                if lam > 1e8:  # no step lowers the cost: a minimum, or hopeless data
                    done = True
                    break
            if done or (math.hypot(*v) * scale < STEP_TOL and math.hypot(*w) * scale < STEP_TOL):
                break
        rms = np.sqrt(max(cost - _prior(u), 0.0) / used)  # of the flux alone
        xi = se3.log_se3(T)
        plausible = bool(np.all(np.abs(self.stiffness @ (xi - self.zero_twist)) <= PLAUSIBLE_RANGE * SENSOR_RANGE))
        plausible = plausible and (u is None or float(np.linalg.norm(u)) <= BACKGROUND_LIMIT_T)
        converged = bool(np.isfinite(rms) and rms <= MAX_RESIDUAL_T and plausible
                         and (done or k < self.max_iterations))
        if converged:
            self.pose, self.background_t = T, _field(u)
        return Estimate(xi, T, converged, k, float(rms), _field(u))

    def wrench(self, estimate: Estimate) -> np.ndarray:
        """w = K xi (N, Nm), the stiffness's wrench at the estimated deflection."""
        return self.stiffness @ estimate.xi


PRIOR_WEIGHT = (BACKGROUND_NOISE_T / BACKGROUND_PRIOR_T) ** 2


def _exp_se3(xi: np.ndarray) -> np.ndarray:
    """`se3.exp_se3` in Python floats: the same formulas (Rodrigues, the left Jacobian, the
    same series near zero), without a dozen numpy calls on 3-vectors every step."""
    v0, v1, v2, w0, w1, w2 = xi.tolist()
    a, b, c = se3._coefficients(math.sqrt(w0 * w0 + w1 * w1 + w2 * w2))
    W = np.array([[0.0, -w2, w1], [w2, 0.0, -w0], [-w1, w0, 0.0]])
    WW = W @ W
    T = np.eye(4)
    T[:3, :3] = _EYE3 + a * W + b * WW
    T[:3, 3] = (_EYE3 + b * W + c * WW) @ (v0, v1, v2)
    return T


def _prior(u: np.ndarray | None) -> float:
    """The background field's prior term of the cost (T^2, as a flux residual's)."""
    return 0.0 if u is None else PRIOR_WEIGHT * float(u @ u)


def _field(u: np.ndarray | None) -> np.ndarray:
    return np.zeros(3) if u is None else u.copy()
