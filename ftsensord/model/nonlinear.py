"""The nonlinear estimator (the paper's future work): the centre-piece pose from all
24 flux values through a magnet field model, then w = K xi.

Forward model: `ftsensord.model.fluxmodel.FluxModel` (dipoles, each chip's own magnet
with its octupole, per-chip response and offset, a uniform background field). Solver:
Levenberg-Marquardt on SE(3) with left perturbations T <- exp(delta) T, analytic
Jacobian (kept while the pose stays near where it was computed: chord steps),
warm-started from the previous pose; damped and step-limited, it reports failure rather
than diverge, and the caller falls back to the linear estimate with a flag.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from ftsensord.model import se3
from ftsensord.model.fluxmodel import FluxModel
from ftsensord.model.linear import SENSOR_RANGE
from ftsensord.model.nlcompiled import solver_for

__all__ = ["Estimate", "FluxModel", "NonlinearEstimator"]

#: Largest step per iteration: 1 mm and 0.05 rad. A full-range deflection is about 6 mm
#: and 0.02 rad; steps this size reach it in a few iterations while keeping the dipole
#: model's 1/r^3 curvature from throwing the pose past a magnet.
MAX_STEP_M = 1e-3
MAX_STEP_RAD = 0.05
#: Converged when a step moves the pose less than 1e-8 m (and `STEP_TOL_RAD`): a hundred
#: times below what the chips resolve (a uT in 1.6 mT at 6 mm is about 1 um of motion).
STEP_TOL = 1e-8
#: The same for turns: 1e-6 rad moves a chip on the 8 mm ring by 8 nm, a hundred times
#: below what it resolves (1 um); the torque it makes (10 Nm/rad) is 1e-5 Nm, 1/300 of
#: the torque noise of one reading. (It was 1e-8 rad, 10^4 below: a third iteration a
#: sample for nothing.)
STEP_TOL_RAD = 1e-6
#: A step that shrank to a tenth or less of the one before, both of one kind (new
#: Jacobians: Newton's quadratic convergence; one kept Jacobian: a chord's linear rate),
#: shows the rate: the steps left then add up to size ratio / (1 - ratio), and when that
#: is under the tolerances the fit ends without paying for another step (from a warm start
#: the second step is about 1/400 of the first: two iterations a sample instead of three).
CONTRACTION = 0.1
#: A Jacobian is reused (a chord step, Gauss-Newton without a new derivative) while the
#: pose is within 40 um and 4 mrad, and the background field within 10 uT, of where it was
#: computed: it changes there by 3 % (p50; 6 % at most with both limits reached at once, on
#: loads to 40 % of range; the field's gradient varies over the 2 mm a magnet is from its
#: nearest saturating chip; the background enters it against 1.6 mT), so each chord step
#: still shrinks the error some thirtyfold. Its end point moves by at most 2.5-2.8 % of the
#: noise's own scatter (tests/test_nonlinear.py's moving load, seeds 6-10; 2.1-2.7 % with
#: 20 um and 2 mrad, where half the moving samples needed a second Jacobian). A
#: sample 10 ms after the last moves the pose by about 6 um and 0.7 mrad (noise, at rest):
#: its fit needs no new Jacobian. A moving load's warm start (`_ahead`) lands 22 um and
#: 1.5 mrad from the fit's answer at p50, 35 um and 2.5 mrad at p90 (1.3 Hz, 40 % of range,
#: benchmarks/performance/nonlinear_cpu.py): one new Jacobian a sample, 1.1 on average.
JACOBIAN_REUSE_M = 40e-6
JACOBIAN_REUSE_TRACE = 1 + 2 * math.cos(4e-3)  # tr(R_J^T R) = 1 + 2 cos(angle): the 4 mrad test
JACOBIAN_REUSE_T = 10e-6
#: A fit whose RMS residual exceeds 1 mT is no pose of this sensor (a chip reading wrong,
#: or garbage), however well it converged: the dipole model's own error is about 0.2 mT RMS
#: at the corners of the range (|F| ~70 N with 0.2 Nm) and 7 uT in the middle (with each
#: chip's own magnet's octupole, 2 uT RMS at 50 N, 10 uT on its worst chip).
MAX_RESIDUAL_T = 1e-3
#: A warm-started fit left with more than 50 uT RMS may sit in a wrong minimum after a
#: fast change of load: a cold start from the rest pose is tried too and the better fit
#: kept. Right poses stay under 20 uT here for |F| up to 50 N along any direction (the
#: dipole model's error at 6 mm is 29 uT, docs/design/physics.md); near the corners of the range
#: and on a sensor whose model fits worse, the cold start is paid more often.
RETRY_RESIDUAL_T = 50e-6
#: The ring of 8 identical chips and magnets reads the same after a turn of 45 degrees
#: about its axis: the flux fixes the pose only up to that turn. A deflection whose
#: wrench K xi exceeds 3 times the sensor's range on any axis (the silicone would have
#: torn) is that twin or garbage, never an answer.
PLAUSIBLE_RANGE = 3.0
#: That turn, 2 pi / 8. A warm and a cold start that both fail with the centre piece
#: turned more than half of it about the shaft have run to the twin (large loads, a chip
#: within 2-3 mm of its magnet); a third start from their answer turned back by it lands
#: in the true pose's basin.
TWIN_TURN_RAD = math.pi / 4
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
#: The step that ends a fit (the steps left foretold under the tolerances) is not checked
#: against the field when it changes no channel by more than 1 uT (a third of the chips'
#: noise): its flux is the Jacobian's prediction, which is off by at most the Jacobian's
#: drift since it was computed (3-6 % of the change within `JACOBIAN_REUSE_M`, measured at
#: loads to 40 % of range: 60 nT, a fiftieth of the noise) and the field's curvature over
#: a step that small (0.4 um at 2 mm from a magnet: under 1 nT). Such a step lowers the
#: linearised cost by construction; an evaluation would only repeat it. (It was 0.1 uT: a
#: moving load's fit then paid a field evaluation for its last step, a third of its work.)
LINEAR_STEP_T = 1e-6
#: Damping up to `WARM_DAMPING` changes a step by under 2e-5 of itself (1e-6 times the scaled
#: J^T J's condition, tests/test_nonlinear.py): the undamped Gauss-Newton gains (`_chord_gains`)
#: serve for a new Jacobian's step as for a kept one's, and the chord steps after (one solve).
UNDAMPED = WARM_DAMPING


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
    ``solver``: "numpy" (`_solve`), "compiled" (the same in C, `nlcompiled`) or "auto" (C when installed).
    """

    def __init__(
        self,
        model: FluxModel,
        stiffness: np.ndarray,
        *,
        max_iterations: int = 30,
        background: bool = True,
        zero_twist: np.ndarray | None = None,
        solver: str = "auto",
    ):
        self.model = model
        self.stiffness = np.asarray(stiffness, dtype=float)
        #: The deflection read at no load (m, rad): the plausibility test judges the wrench
        #: K (xi - zero_twist), the one published, not K xi.
        self.zero_twist = np.zeros(6) if zero_twist is None else np.asarray(zero_twist, dtype=float)
        self.max_iterations = max_iterations
        self.background = background
        self.pose = np.eye(4)  # the warm start: the previous sample's pose
        self.background_t = np.zeros(3)  # and its background field
        #: The last Jacobian per kind of solve (with the background field or not), its pose's
        #: rows and field as lists, and its count (`_made` when it was made): `_linearise`
        #: reuses it near there.
        self._jacobians: dict[bool, tuple[list[list[float]], list[float] | None, np.ndarray, int]] = {}
        self._made = 0  # the Jacobians numpy's solve has made: each one's count (`jacobian_at`)
        #: The last converged fit's pose, field, kind (with the field or not) and predicted
        #: flux: a warm start from that pose and field needs no prediction of its own.
        self._end: tuple[np.ndarray, np.ndarray, bool, np.ndarray | None] | None = None
        #: The poses before and after the last sample's fit (None after a failed one): the
        #: warm start follows the motion between them (`_ahead`).
        self._motion: tuple[np.ndarray, np.ndarray] | None = None
        self._gains: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # `_chord_gains`' last
        self.compiled = solver_for(solver, chips=model.geometry.n_chips)  # None: numpy's

    def estimate(
        self, b: np.ndarray, usable: np.ndarray | None = None, start: np.ndarray | None = None
    ) -> Estimate:
        """The pose that explains flux ``b`` (3n,) on the usable chips (default all).

        Starts from ``start`` (the background field from zero); without one, from the
        previous converged pose and field, and when that fails or fits worse than
        `RETRY_RESIDUAL_T`, from the rest pose too; when both fail near the ring's
        twin (`TWIN_TURN_RAD`), from the twin turned back. Never raises on bad data: an
        estimate that did not converge says so.
        """
        if start is not None:
            return self._cold(b, usable, start)
        before = self.pose
        warm = self._solve(b, usable, self._ahead(before), self.background_t, self.background, WARM_DAMPING)
        if warm.converged and warm.rms_residual_t <= RETRY_RESIDUAL_T:
            self._motion = (before, warm.pose)
            return warm
        tries = [warm, self._cold(b, usable, np.eye(4))]
        twist = min(tries, key=lambda e: e.rms_residual_t).xi[5]
        if not any(e.converged for e in tries) and abs(twist) > TWIN_TURN_RAD / 2:
            # Nearer the ring's twin than the rest pose: its answer turned back by 45 deg.
            back = np.eye(4)
            back[:3, :3] = se3.exp_so3(np.array([0.0, 0.0, -math.copysign(TWIN_TURN_RAD, twist)]))
            tries.append(self._cold(b, usable, back @ min(tries, key=lambda e: e.rms_residual_t).pose))
        best = min(tries, key=lambda e: (not e.converged, e.rms_residual_t))
        if best.converged:
            self.pose, self.background_t = best.pose, best.background_t
        self._motion = (before, best.pose) if best.converged else None
        return best

    def _ahead(self, pose: np.ndarray) -> np.ndarray:
        """Where the warm start begins: ``pose`` (the last fit's) moved on by the last
        sample's motion (`se3.continued`) when it moved beyond `JACOBIAN_REUSE_M` or
        4 mrad (a moving load: the next pose is that much further, its second difference
        some 40 times less at 1.3 Hz and 100 Hz) and within one step's limits (beyond is a
        jump, not a motion to go on with); else ``pose`` (at rest: the noise, doubled)."""
        motion = self._motion
        if motion is None or motion[1] is not pose or _near(pose, motion[0].tolist(), None, None):
            return pose  # none yet, the pose set since, or at rest
        move_on = se3.continued if self.compiled is None else self.compiled.continued  # the same in C
        ahead, moved_m, turned_rad = move_on(motion[0], pose)
        return pose if moved_m > MAX_STEP_M or turned_rad > MAX_STEP_RAD else ahead

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

    def _solve(
        self,
        b: np.ndarray,
        usable: np.ndarray | None,
        start: np.ndarray,
        u0: np.ndarray,
        background: bool,
        damping: float = 1e-3,
    ) -> Estimate:
        if self.compiled is not None:
            # globals(): this module's constants, read every call (as below), no import circle
            return Estimate(*self.compiled.solve(self, b, usable, start, u0, background, damping, globals()))
        b = np.asarray(b, dtype=float)
        T = np.asarray(start, dtype=float)  # never changed in place: the field kept for it stays right
        u = np.array(u0, dtype=float) if background else None
        usable = None if usable is None else np.asarray(usable, bool)
        if usable is None or usable.all():
            channels: slice | np.ndarray = slice(None)  # every chip usable (the usual case): a view
        else:
            channels = np.repeat(usable, 3)
        used = b.size if isinstance(channels, slice) else int(channels.sum())
        # The unknowns need as many channels: 6 for the pose, 9 with the background field.
        if used < (9 if background else 6) or not np.isfinite(b[channels]).all():
            return Estimate(se3.log_se3(T), T, False, 0, np.inf)
        lam = damping  # Marquardt's damping, relative to the diagonal of J^T J
        cost, done, k = np.inf, False, 0
        # The previous step's size (m, rad), its kind and the Jacobian it was taken with.
        last: tuple[tuple[float, float], object, np.ndarray] | None = None
        # The flux predicted at T, once known: from a warm start, the last fit's at its end.
        kept = self._end
        pred = (
            kept[3]
            if kept is not None and kept[0] is start and kept[1] is u0 and kept[2] == background
            else None
        )
        r: np.ndarray = np.empty(0)  # the residual (made at the first step),
        r_of: np.ndarray | None = None  # and the prediction it is of
        for k in range(1, self.max_iterations + 1):
            pred, J_full, fresh = self._linearise(T, u, background, pred)
            if pred is not r_of:
                r, r_of = (b - pred)[channels], pred
                cost = float(r @ r) + _prior(u)
            chord = used == b.size and (not fresh or lam <= UNDAMPED)  # Gauss-Newton's gains serve
            if not chord:
                JtJ, Jtr = _normal(J_full[channels], r, u)
            # The rate is seen from two steps of one kind: both with new Jacobians (Newton's
            # quadratic convergence) or both with the same one (a chord's linear rate: the
            # step that made a Jacobian, then a step with it kept, are two of the same chord).
            kind = NEW if fresh else J_full
            while True:
                try:  # J^T J singular (undamped or damped: a pose no chip sees move) is a refusal
                    if chord:
                        self._gains = _chord_gains(J_full, self._gains)
                        step = self._gains[1] @ r if u is None else self._gains[1] @ r - self._gains[2] @ u
                    else:
                        damped = JtJ.copy()
                        damped.flat[:: damped.shape[0] + 1] *= 1 + lam  # JtJ + lam diag(JtJ)
                        step = np.linalg.solve(damped, Jtr)
                except np.linalg.LinAlgError:
                    return Estimate(se3.log_se3(T), T, False, k, np.sqrt(cost / used), _field(u))
                # 1e-300: a zero step needs no limit (and must not divide by zero). The
                # background field enters linearly: its step needs no limit of its own.
                v0, v1, v2, w0, w1, w2 = step.tolist()[:6]
                size = (math.sqrt(v0 * v0 + v1 * v1 + v2 * v2), math.sqrt(w0 * w0 + w1 * w1 + w2 * w2))
                scale = min(1.0, MAX_STEP_M / max(size[0], 1e-300), MAX_STEP_RAD / max(size[1], 1e-300))
                if scale < 1.0:
                    step, size = step * scale, (size[0] * scale, size[1] * scale)
                T_new = se3.exp_se3(step) @ T
                u_new = None if u is None else u + step[6:]
                final = _within(size) or (
                    last is not None
                    and (last[1] is kind or last[2] is J_full)
                    and _within(_left(size, last[0]))
                )
                change = J_full @ step if final else None
                if change is not None and np.abs(change).max() <= LINEAR_STEP_T:
                    pred_new = pred + change  # the last step, too small to need the field (`LINEAR_STEP_T`)
                else:
                    pred_new = self.model.predict(T_new, u_new)
                r_new = (b - pred_new)[channels]
                cost_new = float(r_new @ r_new) + _prior(u_new)
                if cost_new <= cost:
                    T, u, lam, pred, cost = T_new, u_new, max(lam / 3, 1e-9), pred_new, cost_new
                    r, r_of = r_new, pred_new
                    break
                if _within(size):  # at the minimum already
                    done = True
                    break
                if not fresh:  # a kept Jacobian's step failed: take a new one, not more damping
                    self._jacobians.clear()
                    break
                lam *= 4
                if chord:  # a new Jacobian's undamped step failed: damped solves from here
                    chord = False
                    JtJ, Jtr = _normal(J_full[channels], r, u)
                if lam > 1e8:  # no step lowers the cost: a minimum, or hopeless data
                    done = True
                    break
            if not fresh and not self._jacobians:
                continue
            if done or final:
                break
            last = (
                (size, kind, J_full) if scale == 1.0 else None
            )  # a limited step says nothing of convergence
        rms = math.sqrt(max(cost - _prior(u), 0.0) / used)  # of the flux alone
        xi = se3.log_se3(T)
        plausible = bool((np.abs(self.stiffness @ (xi - self.zero_twist)) <= PLAUSIBLE_WRENCH).all())
        plausible = plausible and (u is None or math.sqrt(float(u @ u)) <= BACKGROUND_LIMIT_T)
        converged = bool(
            math.isfinite(rms) and rms <= MAX_RESIDUAL_T and plausible and (done or k < self.max_iterations)
        )
        if converged:
            self.pose, self.background_t = T, _field(u)
            self._end = (T, self.background_t, background, pred)
        return Estimate(xi, T, converged, k, rms, _field(u))

    def _linearise(
        self, T: np.ndarray, u: np.ndarray | None, background: bool, pred: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray, bool]:
        """Flux at (T, u) (``pred`` when known), a Jacobian, and whether it is new
        (`_kept_jacobian`)."""
        J, made = self._kept_jacobian(T, u, background)
        if made is not None:
            return made, J, True
        return self.model.predict(T, u) if pred is None else pred, J, False

    def _kept_jacobian(
        self, T: np.ndarray, u: np.ndarray | None, background: bool
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """The Jacobian at (T, u) and, when it is new, the flux there (else None): the one kept
        from a pose within `JACOBIAN_REUSE_M` and 4 mrad (and a field within
        `JACOBIAN_REUSE_T`), else a new one, kept from here (the compiled solve's `linearise`
        is the same rule)."""
        kept = self._jacobians.get(background)
        if kept is not None and _near(T, kept[0], u, kept[1]):
            return kept[2], None
        pred, J = self.model.predict_and_jacobian(T, u, background)
        self._made += 1
        self._jacobians[background] = (T.tolist(), None if u is None else u.tolist(), J, self._made)
        return J, pred

    def jacobian_at(
        self, T: np.ndarray, u: np.ndarray, known: tuple[object, int] | None = None
    ) -> tuple[tuple[object, int], np.ndarray | None]:
        """The flux model's Jacobian at pose ``T`` and background field ``u`` with the field's
        columns (3n x 9, every channel), as the solve with the field uses it: the one it keeps,
        made within `JACOBIAN_REUSE_M`, 4 mrad and `JACOBIAN_REUSE_T` of (T, u), else a new
        one, kept for the solves after (at the last fit's pose, a warm start's). With its
        version: the solve that keeps it (numpy's: this estimator; the compiled one's) and its
        count there, new with each Jacobian made, so a cache of what was made from it stays
        right while the version does. None instead of the Jacobian when its version is
        ``known`` (the caller has it). Do not change it in place."""
        if self.compiled is not None:
            mine = None if known is None or known[0] is not self.compiled else known[1]  # this solve's count
            count, J = self.compiled.jacobian(self, T, u, globals(), mine)
            return (self.compiled, count), J
        J = self._kept_jacobian(T, u, True)[0]
        version = (self, self._jacobians[True][3])
        return version, None if version == known else J

    def gains(self, J: np.ndarray, channels: np.ndarray | None = None) -> np.ndarray:
        """(J_S^T J_S + P)^-1 J_S^T (9 x the channels used): how the solve's answer (pose and
        field) moves with the flux of ``channels`` (bool per channel; None: every one) near
        where J (`jacobian_at`) was made, P the background field's prior. With every channel,
        the chord steps' gains (`_chord_gains`; the compiled solve's from the factors it
        keeps), kept while J is."""
        if channels is None or channels.all():
            if self.compiled is not None:
                return self.compiled.chord_gains(J)
            self._gains = _chord_gains(J, self._gains)
            return self._gains[1]
        return _chord_gains(J[channels], None)[1]

    def wrench(self, estimate: Estimate) -> np.ndarray:
        """w = K xi (N, Nm), the stiffness's wrench at the estimated deflection."""
        return self.stiffness @ estimate.xi


PRIOR_WEIGHT = (BACKGROUND_NOISE_T / BACKGROUND_PRIOR_T) ** 2
PRIOR_EYE = PRIOR_WEIGHT * np.eye(3)
PRIOR_EYE.setflags(write=False)
PRIOR_9 = np.zeros((9, 9))  # P: the prior on the 9 unknowns (the background field's 3 only)
PRIOR_9[6:, 6:] = PRIOR_EYE
PRIOR_9.setflags(write=False)
PLAUSIBLE_WRENCH = PLAUSIBLE_RANGE * SENSOR_RANGE
NEW = object()  # the kind of a step taken with a new Jacobian


def _near(T: np.ndarray, rows_J: list[list[float]], u: np.ndarray | None, u_J: list[float] | None) -> bool:
    """Whether pose T (and field u) is within `JACOBIAN_REUSE_M`, 4 mrad (and
    `JACOBIAN_REUSE_T`) of the pose with rows ``rows_J`` (and field ``u_J``)."""
    # In floats: a dozen numpy calls on 3-vectors would cost more than the test saves.
    (a0, a1, a2, a3), (b0, b1, b2, b3), (c0, c1, c2, c3), _ = T.tolist()
    (d0, d1, d2, d3), (e0, e1, e2, e3), (f0, f1, f2, f3), _ = rows_J
    trace = a0 * d0 + a1 * d1 + a2 * d2 + b0 * e0 + b1 * e1 + b2 * e2 + c0 * f0 + c1 * f1 + c2 * f2
    return (
        trace >= JACOBIAN_REUSE_TRACE  # tr(R_J^T R) = 1 + 2 cos(angle)
        and math.dist((a3, b3, c3), (d3, e3, f3)) <= JACOBIAN_REUSE_M
        and (u is None or (u_J is not None and math.dist(u_J, u.tolist()) <= JACOBIAN_REUSE_T))
    )


def _chord_gains(
    J: np.ndarray, kept: tuple[np.ndarray, np.ndarray, np.ndarray] | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gauss-Newton's step for a kept Jacobian J (every channel), (J, G, G_u) with the step
    G r - G_u u, G = (J^T J + P)^-1 J^T, G_u = (J^T J + P)^-1 P (P the background's prior
    on its 3 unknowns); ``kept`` when it is J's. Undamped: a chord step is taken only near
    where J was."""
    if kept is not None and kept[0] is J:
        return kept
    if J.shape[1] == 6:  # no background field: no prior, and no G_u
        return J, np.linalg.solve(J.T @ J, J.T), PRIOR_9[:6, 6:]
    gains = np.linalg.solve(J.T @ J + PRIOR_9, np.concatenate([J.T, PRIOR_9[:, 6:]], axis=1))
    return J, gains[:, : J.shape[0]], gains[:, J.shape[0] :]


def _normal(J: np.ndarray, r: np.ndarray, u: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """J^T J and J^T r with the background field's prior rows, (noise / prior) (u + du) = 0."""
    JtJ, Jtr = J.T @ J, J.T @ r
    if u is not None:
        JtJ[6:, 6:] += PRIOR_EYE
        Jtr[6:] -= PRIOR_WEIGHT * u
    return JtJ, Jtr


def _left(size: tuple[float, float], last: tuple[float, float]) -> tuple[float, float]:
    """How far the fit has left to go (m, rad), foretold from this step and the one
    before: where it converges (each step at most `CONTRACTION` of the one before) all the
    steps left add up to at most size ratio / (1 - ratio), ratio = size / last; inf where
    that is not seen."""
    if min(last) <= 0:
        return math.inf, math.inf
    ratio = max(size[0] / last[0], size[1] / last[1])
    if ratio > CONTRACTION:
        return math.inf, math.inf
    return size[0] * ratio / (1 - ratio), size[1] * ratio / (1 - ratio)


def _within(size: tuple[float, float]) -> bool:
    """A step (m, rad) under the tolerances: the pose is where the flux puts it."""
    return size[0] < STEP_TOL and size[1] < STEP_TOL_RAD


def _prior(u: np.ndarray | None) -> float:
    """The background field's prior term of the cost (T^2, as a flux residual's)."""
    return 0.0 if u is None else PRIOR_WEIGHT * float(u @ u)


def _field(u: np.ndarray | None) -> np.ndarray:
    return np.zeros(3) if u is None else u.copy()
