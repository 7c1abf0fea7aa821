"""Calibration (paper, eqs. 12-18): fit A and K, and the zero, from a dataset.

Steps: the position map of each chip from its sweep (eq. 1); the deflection
twist of every pose by registration (eqs. 5-11); A from twists and flux
(eq. 15, A = Xi B^+), K from wrenches (eq. 18, K = W (A B)^+), with an explicit
zero: w = K A (b - b0). Before fitting, the dataset is checked (`checks`: numbers,
units, signs, dead or stuck chips, the magnets' polarity); the wrenches must excite
all six axes independently (`excitation`), or K is not identifiable and the fit
refuses, naming what the plan lacks. A few outlier poses are left out, named
(`screening`), the chips' order is checked against their places, and a K that is not
positive definite is refused too.

The room's field (the Earth's, fixed in the world) turns in the sensor's frame
as the robot turns the sensor. Uniform, it adds R_i^T u to chip i (u the field
in {0}): 3 directions of the 24-dim flux (`room_directions`). The fit can
project them out of the flux before fitting A, so that K A rejects any uniform
field; the directions are measured from no-load poses at several orientations,
or taken from the nominal geometry (docs/guide/calibration.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ftsensord.calibration.checks import (
    check_chips,
    check_finite,
    check_flux_scale,
    check_loads,
    check_plausible,
    check_polarity,
    check_stiffness,
    duplicate_poses,
)
from ftsensord.calibration.dataset import AXES, Dataset
from ftsensord.calibration.excitation import CONDITION_WARN, check_excitation
from ftsensord.calibration.rig import simulate_sweeps
from ftsensord.calibration.screening import check_chip_order, leave_out_outliers
from ftsensord.errors import CalibrationError
from ftsensord.model.geometry import SensorGeometry
from ftsensord.model.linear import (
    SENSOR_RANGE,
    LinearModel,
    PositionMap,
    deflection_twist,
    fit_position_map,
)
from ftsensord.sim.chip import NOISELESS

#: Parameters of one row of the affine flux-to-twist fit: 24 slopes and an offset.
MIN_FIT_POSES = 26
#: How the fit treats the room's field: "none" (a field-free room), "geometry" (project
#: out the directions the nominal chip orientations give), "measured" (those the no-load
#: poses span), "auto" ("measured" when the dataset has enough no-load poses, else "none").
ROOM_FIELD_MODES = ("auto", "none", "geometry", "measured")
#: No-load poses needed to measure the 3 room directions: 4 span them once centred; 6
#: leave a spare pose per direction to test that no 4th direction varies.
MIN_NO_LOAD_POSES = 6
#: The room's 3 directions must stand this far above the no-load noise floor to be
#: measured (a 50 uT field turned through the room stands ~100 times above it; a
#: field-free room not at all): below it they are noise, and the nominal ones are used.
ROOM_SIGNAL_FACTOR = 10.0
#: A 4th direction varying at no load above this many times the noise floor is not a
#: uniform field: a rod or mass left on (its weight turns with the sensor), or a field
#: that is not uniform (steel or a motor near the sensor). 3x: pure noise stays under
#: the floor itself (Marchenko-Pastur edge) with margin.
ROOM_EXTRA_FACTOR = 3.0


class RoomFieldError(CalibrationError):
    """The no-load check's refusal: a 4th flux direction varies at no load. ``after_load_s``:
    how long after a load came off the first no-load pose that followed one was read (s), None
    when none followed a load or the poses' times were not recorded (`after_load_s`);
    ``figures``: the singular values and the noise floor as the message gives them (uT)."""

    def __init__(self, message: str, after_load_s: float | None, figures: str):
        super().__init__(message)
        self.after_load_s, self.figures = after_load_s, figures


def after_load_s(dataset: Dataset) -> float | None:
    """The shortest time (s) from a load coming off (the next pose's applied time) to the first
    reading of a no-load pose after it, over the no-load poses recorded after a loaded one;
    None when none was, or the poses' times were not recorded."""
    if dataset.times_s is None:
        return None
    order = np.argsort(dataset.times_s[:, 0], kind="stable")
    # A load: a pose of the plan that carries one (a no-load pose's own wrench is none by its split).
    loaded = (dataset.split != "no-load") & (np.linalg.norm(dataset.wrench, axis=1) > 0)
    shortest, off = None, None  # off: when the last load came off
    for j, k in enumerate(order):
        if loaded[k]:
            off = dataset.times_s[order[j + 1], 0] if j + 1 < len(order) else None
        elif dataset.split[k] == "no-load" and off is not None:
            wait = float(dataset.times_s[k, 1] - off)
            shortest = wait if shortest is None else min(shortest, wait)
    return shortest


def noise_floor(flux_sem: np.ndarray) -> float:
    """Largest singular value pure noise reaches in an n x d flux matrix (T).

    A Gaussian n x d matrix of standard deviation sigma has its largest
    singular value near sigma (sqrt(n) + sqrt(d)) (Marchenko-Pastur edge);
    flux directions below that are noise, and inverting them would amplify it.
    """
    n, d = flux_sem.shape
    return float(np.median(flux_sem)) * (math.sqrt(n) + math.sqrt(d))


@dataclass(frozen=True)
class LinearFit:
    model: LinearModel
    flux_rank: int  # directions of the centred flux kept above the noise floor
    floor_t: float


def fit_linear(
    flux: np.ndarray,
    twist: np.ndarray,
    wrench: np.ndarray,
    floor_t: float = 0.0,
    room: np.ndarray | None = None,
    zero: tuple[np.ndarray, np.ndarray] | None = None,
) -> LinearFit:
    """A, K and the zero from flux (n, 24; T), twists (n, 6) and wrenches (n, 6).

    A is the least-squares map of centred flux to centred twist, through the
    flux directions above ``floor_t`` (a truncated pseudo-inverse); K and an
    offset c fit W = (A (B - mean)) K^T + c; the zero b0 then solves
    K A (b_mean - b0) = c with the least change along A's row space.
    ``room`` (24 x 3, orthonormal) are flux directions projected out of the
    centred flux first: A is then blind to them (A room = 0), and so is K A.

    With ``zero`` (no-load poses' flux (m, 24) and twists (m, 6)) the zero is measured:
    b0 their mean flux, A and K fitted through it. The affine fit's zero, extrapolated
    from the loaded poses, is bent by the room's projection (figures: docs/guide/calibration.md,
    "The zero")."""
    if zero is not None:
        return _fit_through_zero(flux, twist, wrench, floor_t, room, zero)
    b_mean = flux.mean(axis=0)
    centred = flux - b_mean
    if room is not None:
        centred = centred - (centred @ room) @ room.T
    u, s, vt = np.linalg.svd(centred, full_matrices=False)
    # Without a noise floor, numpy's own rank rule: round-off of the SVD itself.
    tol = max(floor_t, s[0] * max(centred.shape) * np.finfo(float).eps)
    keep = s > tol
    pinv = (vt[keep].T / s[keep]) @ u[:, keep].T  # (24, n)
    A = (pinv @ (twist - twist.mean(axis=0))).T
    xi = centred @ A.T  # the fitted twists, centred
    z = np.column_stack([xi, np.ones(len(flux))])
    coef, *_ = np.linalg.lstsq(z, wrench, rcond=None)
    K, c = coef[:6].T, coef[6]
    b0 = b_mean - np.linalg.pinv(A) @ np.linalg.solve(K, c)
    # The forward model for degraded mode: flux from twist, b - b0 = H xi.
    Ht, *_ = np.linalg.lstsq(xi, centred, rcond=None)
    return LinearFit(LinearModel(K, A, b0, Ht.T, room=room), int(keep.sum()), float(floor_t))


def _fit_through_zero(
    flux: np.ndarray,
    twist: np.ndarray,
    wrench: np.ndarray,
    floor_t: float,
    room: np.ndarray | None,
    zero: tuple[np.ndarray, np.ndarray],
) -> LinearFit:
    """`fit_linear` with the zero measured: b - b0 maps to xi - xi0 through the origin."""
    b0, xi0 = zero[0].mean(axis=0), zero[1].mean(axis=0)
    centred = flux - b0
    if room is not None:
        centred = centred - (centred @ room) @ room.T
    u, s, vt = np.linalg.svd(centred, full_matrices=False)
    # Without a noise floor, numpy's own rank rule: round-off of the SVD itself.
    keep = s > max(floor_t, s[0] * max(centred.shape) * np.finfo(float).eps)
    A = (((vt[keep].T / s[keep]) @ u[:, keep].T) @ (twist - xi0)).T
    xi = centred @ A.T
    Kt, *_ = np.linalg.lstsq(xi, wrench, rcond=None)
    Ht, *_ = np.linalg.lstsq(xi, centred, rcond=None)  # degraded mode's forward model
    return LinearFit(LinearModel(Kt.T, A, b0, Ht.T, room=room), int(keep.sum()), float(floor_t))


def rmse(model: LinearModel, dataset: Dataset) -> np.ndarray:
    """Root mean square error per axis (N, Nm) of the model on a dataset."""
    return np.sqrt(np.mean((model.wrench(dataset.flux_t) - dataset.wrench) ** 2, axis=0))


#: Loads (N, Nm) the linear map's error is read at over the calibration's range, through its
#: own flux model (`procedure.linear_error_model`): 2000 with every axis loaded at once and 2000
#: with one to three axes alone (`range_loads`), about 150 loads for each of an axis's 25
#: coefficients (`error_model`) in each kind: with 400 a part's coverage at 1 sigma moved by 6
#: points from one set of draws to another; 0.4 s at calibration.
RANGE_LOADS = 2000
#: The draws' seed: a calibration file is the same each time it is made from one dataset.
RANGE_SEED = 6


def range_loads(wrench_range: np.ndarray, n: int = RANGE_LOADS) -> np.ndarray:
    """2 ``n`` loads (N and Nm) within +-``wrench_range``: ``n`` with every axis drawn uniformly
    at once, and ``n`` with each axis loaded only with a chance of 1/6, 2/6 or 3/6 (a push
    along one axis, a force at an arm). Both kinds: fitted on loads of every axis at once
    alone, the form's sums put an axis's error at a pure load on the other axes' terms, and a
    pure 1.8 N Fy's cross-talk onto Fz and Mx came out 15-20 times the sigma's model part."""
    rng = np.random.default_rng(RANGE_SEED)
    span = np.asarray(wrench_range, dtype=float)
    every = rng.uniform(-1.0, 1.0, (n, 6)) * span
    chance = rng.choice([1 / 6, 2 / 6, 3 / 6], (n, 1))
    some = rng.uniform(-1.0, 1.0, (n, 6)) * span * (rng.uniform(size=(n, 6)) < chance)
    return np.vstack([every, some])


def error_model(
    error: np.ndarray,
    wrench: np.ndarray,
    noise_var: np.ndarray | float = 0.0,
    source: str = "poses",
    within: np.ndarray | None = None,
    applied: np.ndarray | None = None,
    tared: bool = False,
) -> dict[str, Any] | None:
    """Each axis's error as a function of the load, for each sample's sigma
    (`processing.uncertainty.ModelError`): per axis k,

        error_k^2 ~ rest_k^2 + sum_j spread_kj |w_j| + sum_j (gain_kj w_j)^2
                    + sum_j (curvature_kj w_j^2)^2 + sum_j (beyond_kj max(0, |w_j| - within_j))^2

    (with ``within``, each w_j in the first sums held at +-within_j) fitted by non-negative least
    squares on ``error`` (loads x 6, N and Nm) at ``wrench`` (loads x 6: the estimates, as a
    sample's sigma is asked at the wrench it reads), less ``noise_var`` (6, or per load: loads x
    6), the part of each squared error that is the pose's own reading noise, not the model's.

    The form: a map's error expanded in the load, a gain or cross-talk term (error_k = G_kj w_j,
    of either sign as the load turns: its square's mean over the loads' directions is sum_j
    G_kj^2 w_j^2), a curvature term (the field's and the silicone's bending), and the error at no
    load. The spread term is the part of the error's square that comes in at small loads already
    and grows slower than w^2: the loads of one axis change the gains of the others, so an
    axis's error at a given load of its own spreads with the rest of the load, which the sums of
    single axes' powers do not hold. Without it the fit puts that part into a constant (0.16 N
    on Fy of the linear map on three as-built parts), which after a tare at no load is wrong
    at rest, and left out, Fy's samples were within 1 sigma for 45-49 % of the range's loads.
    ``tared``: the errors were read from a tare at no load (zero there by construction): no rest
    term. With ``within`` (6, N and Nm: the calibration's range), the first terms are fitted on
    the loads within it alone, and the loads beyond it (check poses) fit the last term, zero
    within: the errors there, tens of times the range, would otherwise set the gain that the
    range's own loads show to be far smaller. Coefficients: rest in N or Nm; spread in N^2 per N
    (Nm^2 per Nm, N^2 per Nm, ...); gain and beyond per unit load; curvature per unit load
    squared. None with fewer loads within than the form's 25 unknowns. ``applied``: the loads
    themselves (loads x 6; default ``wrench``), which tell those within the range from those
    beyond (an estimate of a fit pose's load may read a little past the range that load set).
    ``mean_load``: the RMS over the loads within of the range-scaled norm |w / SENSOR_RANGE|."""
    error, wrench = np.asarray(error, dtype=float), np.asarray(wrench, dtype=float)
    target = error**2 - np.broadcast_to(np.asarray(noise_var, dtype=float), error.shape)
    inside = np.ones(len(error), dtype=bool)
    if within is not None:
        within = np.asarray(within, dtype=float)
        # 1e-9 of the range: a fit pose's own load is within the range it sets, to round-off.
        inside = np.all(np.abs(wrench if applied is None else applied) <= within * (1 + 1e-9), axis=1)
    if inside.sum() < 25:
        return None

    def design(w: np.ndarray) -> np.ndarray:
        scaled = np.abs(w) / SENSOR_RANGE
        rest = np.zeros(len(w)) if tared else np.ones(len(w))
        return np.column_stack([rest, scaled, scaled**2, scaled**4])

    coef = np.array([_nonnegative_fit(design(wrench[inside]), target[inside, k]) for k in range(6)])
    beyond = np.zeros((6, 6))
    if within is not None and not inside.all():
        # The range's form held at its edge (its curvature term, fitted within, would grow as
        # w^4 beyond): what it leaves, the last term fits.
        held = design(np.minimum(np.abs(wrench[~inside]), within))
        # The excess of the load itself: an estimate's own error would otherwise put an excess
        # on an axis the poses never loaded (Mz read 0.2 Nm for none hung).
        loads = wrench if applied is None else np.asarray(applied, dtype=float)
        excess = np.maximum(np.abs(loads[~inside]) - within, 0.0) / SENSOR_RANGE
        left = target[~inside] - held @ coef.T
        beyond = np.sqrt(np.array([_nonnegative_fit(excess**2, left[:, k]) for k in range(6)])) / SENSOR_RANGE
    scaled = wrench[inside] / SENSOR_RANGE
    return {
        "rest": dict(zip(AXES, np.sqrt(coef[:, 0]).tolist())),
        "spread": {a: row.tolist() for a, row in zip(AXES, coef[:, 1:7] / SENSOR_RANGE)},
        "gain": {a: row.tolist() for a, row in zip(AXES, np.sqrt(coef[:, 7:13]) / SENSOR_RANGE)},
        "curvature": {a: row.tolist() for a, row in zip(AXES, np.sqrt(coef[:, 13:]) / SENSOR_RANGE**2)},
        "beyond": {a: row.tolist() for a, row in zip(AXES, beyond)},
        "within": None if within is None else within.tolist(),
        "mean_load": float(np.sqrt(np.mean(np.sum(scaled**2, axis=1)))),
        "loads": int(inside.sum()),
        "loads_beyond": int((~inside).sum()),
        "source": source,
    }


def _nonnegative_fit(design: np.ndarray, target: np.ndarray) -> np.ndarray:
    """`nonnegative_least_squares` with each column at unit RMS for the solve (the quartic
    ones are 1e-6 of the others at the plan's loads), its coefficients scaled back."""
    norms = np.sqrt(np.mean(design**2, axis=0))
    norms[norms == 0] = 1.0  # a column no load moves: zero, and so its coefficient
    return nonnegative_least_squares(design / norms, target) / norms


def pose_noise(M: np.ndarray, poses: Dataset) -> np.ndarray:
    """Each pose's reading noise through the map ``M`` (6 x 24): its mean flux's standard errors
    (``flux_sem_t``) propagated, a variance per axis (poses x 6; zeros when not recorded)."""
    if poses.flux_sem_t.shape != poses.flux_t.shape:
        return np.zeros((len(poses), 6))
    return poses.flux_sem_t**2 @ (M**2).T


def nonnegative_least_squares(D: np.ndarray, y: np.ndarray) -> np.ndarray:
    """min |D c - y| over c >= 0 (Lawson and Hanson's active set: a column enters while the
    gradient favours it, leaves when its coefficient would turn negative; at most 3 passes a
    column, which these small problems never reach)."""
    n = D.shape[1]
    c = np.zeros(n)
    free = np.zeros(n, dtype=bool)
    # Round-off of the gradient D^T r, as numpy's rank rule reckons it.
    tol = (
        10
        * np.finfo(float).eps
        * float(np.abs(D).sum(axis=0).max())
        * max(D.shape)
        * max(1.0, float(np.abs(y).max()))
    )
    for _ in range(3 * n):
        gradient = D.T @ (y - D @ c)
        gradient[free] = -np.inf
        if free.all() or gradient.max() <= tol:
            break
        free[int(np.argmax(gradient))] = True
        for _ in range(n):  # each pass frees a coefficient or ends
            z = np.zeros(n)
            z[free] = np.linalg.lstsq(D[:, free], y, rcond=None)[0]
            if np.all(z[free] > 0):
                c = z
                break
            # Step from c towards z until the first free coefficient reaches zero; it leaves.
            falling = free & (z <= 0)
            step = float(np.min(c[falling] / (c[falling] - z[falling])))
            c = c + step * (z - c)
            free &= c > 0
            c[~free] = 0.0
    return c


def singular_values_ka(model: LinearModel) -> dict[str, list[float]]:
    """Singular values of K A for forces (N/uT) and torques (Nm/uT), section VI."""
    ka_per_ut = model.KA * 1e-6
    return {
        "forces": np.linalg.svd(ka_per_ut[:3], compute_uv=False).tolist(),
        "torques": np.linalg.svd(ka_per_ut[3:], compute_uv=False).tolist(),
    }


def position_maps(dataset: Dataset, geometry: SensorGeometry) -> tuple[PositionMap, str]:
    """Per-chip (M, o) from the dataset's sweeps, or from a model sweep if it has none."""
    sweeps, source = dataset.sweeps, "sweeps recorded in the dataset"
    missing = [a for a in dataset.addresses if a not in sweeps]
    if missing:
        sweeps = {**simulate_sweeps(missing, geometry, noise=NOISELESS), **sweeps}
        source = (
            f"model sweep (exact cylinder field, nominal geometry) for "
            f"{', '.join(f'0x{a:02X}' for a in missing)}"
            + ("" if len(missing) == len(dataset.addresses) else "; recorded sweeps for the rest")
        )
    fits = []
    for a in dataset.addresses:
        try:
            fits.append(fit_position_map(sweeps[a].flux_t, sweeps[a].position_m))
        except ValueError as exc:
            raise CalibrationError(
                f"{dataset.where()}position_sweeps.0x{a:02X}: chip 0x{a:02X}'s position-map "
                f"sweep cannot give its map: {exc}. Record the sweep again, moving the "
                "magnet along all three axes"
            ) from exc
    return PositionMap(np.array([f[0] for f in fits]), np.array([f[1] for f in fits])), source


def room_directions(
    dataset: Dataset, geometry: SensorGeometry, mode: str = "auto"
) -> tuple[np.ndarray | None, dict]:
    """The 3 flux directions (24 x 3, orthonormal) a uniform room field takes, per ``mode``
    (`ROOM_FIELD_MODES`), and a report of how they were found.

    "measured": the top 3 directions of the centred flux of the unsaturated no-load
    poses (any orientations: the field turns in the sensor's frame, the magnets do
    not move). They hold the as-built chips' tilts and gains, which the nominal
    geometry does not. Refused when a 4th direction varies (no uniform field does).
    """
    if mode not in ROOM_FIELD_MODES:
        raise ValueError(f"room field mode must be one of {ROOM_FIELD_MODES}, got {mode!r}")
    no_load = dataset.select((dataset.split == "no-load") & ~dataset.saturated.any(axis=1))
    asked = mode
    if mode == "auto":
        mode = "measured" if len(no_load) >= MIN_NO_LOAD_POSES else "none"
    if mode == "none":
        _refuse_a_field_left_in(dataset, no_load, asked)
        return None, {"mode": "none", "no_load_poses": len(no_load)}
    if mode == "geometry":
        return geometry.room_directions(), {
            "mode": "geometry",
            "no_load_poses": len(no_load),
            "source": "nominal chip orientations",
        }
    if len(no_load) < MIN_NO_LOAD_POSES:
        raise CalibrationError(
            f"{dataset.where()}{len(no_load)} unsaturated no-load poses: measuring the room "
            f"field's directions needs at least {MIN_NO_LOAD_POSES}, at orientations that "
            "turn every sensor axis through the field"
        )
    centred = no_load.flux_t - no_load.flux_t.mean(axis=0)
    _, sv, vt = np.linalg.svd(centred, full_matrices=False)
    floor = noise_floor(no_load.flux_sem_t) if no_load.samples_per_pose > 1 else 0.0
    report = {
        "mode": "measured",
        "no_load_poses": len(no_load),
        "noise_floor_ut": floor * 1e6,
        "singular_values_ut": (sv[:5] * 1e6).tolist(),
    }
    if len(sv) > 3 and sv[3] > ROOM_EXTRA_FACTOR * floor:
        figures = (
            "singular values "
            + ", ".join(f"{v * 1e6:.3g}" for v in sv[:5])
            + f" uT; noise floor {floor * 1e6:.3g} uT"
        )
        raise RoomFieldError(
            f"{dataset.where()}the no-load poses vary in more than 3 flux directions ({figures}): not a "
            "uniform field alone. Take the rod and mass off for the no-load poses, and move steel and motors "
            "away from the sensor",
            after_load_s(dataset),
            figures,
        )
    if sv[2] <= ROOM_EXTRA_FACTOR * floor < ROOM_SIGNAL_FACTOR * floor <= sv[0]:
        # A field stands well above the noise, but its 3rd direction is at the noise (where a
        # 4th must stay): the poses turned the sensor about one axis only, so the field along
        # it never changed. Over poses spread on the sphere the three stand alike (~1.1:1).
        # (The middle comparison only says floor > 0: a noiseless dataset has no such band.
        # A 3rd direction between the two factors, above the noise yet too weak to measure,
        # takes the nominal directions below, as a field-free room does: not refused.)
        raise CalibrationError(
            f"{dataset.where()}the no-load poses turn the sensor about one axis only: the room field varies in 2 "
            "flux directions (singular values "
            + ", ".join(f"{v * 1e6:.3g}" for v in sv[:3])
            + f" uT; noise floor "
            f"{floor * 1e6:.3g} uT), its 3rd is not seen, and the directions measured would leave it in. Record "
            "no-load poses at orientations spread over the sphere (the shaft tilted every way, turned about the "
            "vertical too), not by turning one joint"
        )
    if sv[2] < ROOM_SIGNAL_FACTOR * floor:
        # The room field is too weak to measure its directions: nothing to reject that the
        # noise does not hide, so the nominal directions are as good and cost the same.
        report.update(
            mode="geometry",
            source="nominal chip orientations (the no-load poses show no 3rd room "
            f"field direction above {ROOM_SIGNAL_FACTOR:g} x the noise floor)",
        )
        return geometry.room_directions(), report
    report["source"] = "no-load poses"
    return vt[:3].T, report


def _refuse_a_field_left_in(dataset: Dataset, no_load: Dataset, asked: str) -> None:
    """Refuse a fit that takes the room as field-free when its own no-load poses show a field
    turning with the sensor (their centred flux's largest direction above `ROOM_SIGNAL_FACTOR`
    times its noise floor): the fit would take that field for load, and K A comes out bent
    (on the default scene's parts 4-11 times the field-free fit's error, or a K that is not
    positive definite, depending on the plan). Fewer than 2 poses, or single readings (no
    floor), cannot tell: nothing is refused."""
    if len(no_load) < 2 or no_load.samples_per_pose < 2:
        return
    sv = np.linalg.svd(no_load.flux_t - no_load.flux_t.mean(axis=0), compute_uv=False)
    floor = noise_floor(no_load.flux_sem_t)
    if sv[0] <= ROOM_SIGNAL_FACTOR * floor:
        return
    seen = (
        f"the {len(no_load)} no-load poses' flux turns with the sensor ({sv[0] * 1e6:.3g} uT across their "
        f"orientations, {sv[0] / floor:.0f}x the noise floor of {floor * 1e6:.3g} uT): a room field, which the fit "
        "would take for load"
    )
    if asked == "none":
        raise CalibrationError(
            f"{dataset.where()}room field 'none' takes the room as field-free, but {seen}. Use 'auto' or "
            "'measured' (the no-load poses measure its directions), or 'geometry'"
        )
    raise CalibrationError(
        f"{dataset.where()}the room's field cannot be rejected: {seen}, and measuring its directions needs at "
        f"least {MIN_NO_LOAD_POSES} no-load poses. Record {MIN_NO_LOAD_POSES} or more at orientations that "
        "turn every sensor axis through the field (docs/guide/calibration.md), or fit with room field "
        "'geometry' (the nominal directions)"
    )


@dataclass
class CalibrationResult:
    model: LinearModel
    position_map: PositionMap
    report: dict
    wrench_range: np.ndarray  # the largest |w| per axis over the fit poses (N, Nm)
    #: Poses left out beside the saturated ones (logged twice, outliers): a mask over the dataset.
    excluded: np.ndarray | None = None

    @property
    def warnings(self) -> list[str]:
        """What was kept against the data's faults, each with its figure (the report's)."""
        return list(self.report.get("warnings", []))


def check_numbers(dataset: Dataset, geometry: SensorGeometry) -> None:
    """Refuse numbers that cannot be what they claim (`checks`): shapes, no numbers, flux
    no chip reads, wrenches their own masses do not give. First: nothing else is judged on them."""
    if dataset.flux_t.shape[1] != 3 * geometry.n_chips:
        raise CalibrationError(
            f"the dataset has {dataset.flux_t.shape[1] // 3} chips, the geometry {geometry.n_chips}"
        )
    check_finite(dataset)
    check_plausible(dataset)
    check_loads(dataset)


def check_flux(dataset: Dataset, geometry: SensorGeometry) -> None:
    """Refuse flux that is not this sensor's (`checks`): far too small, a dead or stuck chip,
    magnets the other way round. After the plan's checks: those need only the wrenches."""
    check_flux_scale(dataset)
    check_chips(dataset)
    check_polarity(dataset, geometry)


def fit(
    dataset: Dataset, geometry: SensorGeometry | None = None, *, room_field: str = "auto"
) -> CalibrationResult:
    """Fit the linear model to the dataset's "fit" poses and validate on the rest.

    Poses where any chip saturated are left out (and counted); poses logged twice and a
    few outlier poses are left out with a warning naming each (``report["warnings"]``).
    ``room_field`` (`ROOM_FIELD_MODES`) says how a uniform room field is rejected. Raises
    `CalibrationError` when the data are wrong in a way the checks name (`check_numbers`,
    `check_flux`), the wrenches do not excite all six axes, more than a few poses do not
    follow their loads, the chips are out of order, or K is not positive definite.
    """
    geometry = geometry or SensorGeometry.ring()
    check_numbers(dataset, geometry)
    copies, warnings = duplicate_poses(dataset)
    saturated = dataset.saturated.any(axis=1)
    clean = ~saturated & ~copies
    fits = np.flatnonzero((dataset.split == "fit") & clean)
    fit_set = dataset.select(fits)
    if len(fit_set) < MIN_FIT_POSES:
        counts = dataset.saturated[dataset.split == "fit"].sum(axis=0)
        chips = ", ".join(f"0x{a:02X} in {n}" for a, n in zip(dataset.addresses, counts) if n)
        left = int((saturated & (dataset.split == "fit")).sum())
        raise CalibrationError(
            f"{dataset.where()}{len(fit_set)} usable fit poses; at least {MIN_FIT_POSES} are "
            f"needed ({left} left out for saturation"
            + (f": chip {chips} poses" if chips else "")
            + "). A chip saturates near "
            "50 mT: lighter masses, or a magnet further from that chip"
        )
    excitation = check_excitation(fit_set.wrench)
    if not excitation.identifiable:
        raise CalibrationError(
            "K is not identifiable from this dataset: "
            + "; ".join(excitation.describe())
            + f" (rank {excitation.rank} of 6, singular values of the range-scaled wrenches "
            + ", ".join(f"{v:.3g}" for v in excitation.singular_values)
            + "). To fix the plan: "
            + excitation.advice()
            + "."
        )
    check_flux(dataset, geometry)
    room, room_report = room_directions(dataset, geometry, room_field)
    pmap, pmap_source = position_maps(dataset, geometry)
    zero_set = dataset.select((dataset.split == "no-load") & clean)
    raw = np.concatenate([fit_set.flux_t, zero_set.flux_t])
    flux = raw
    if room is not None:
        # The twists are measured on flux with the room's field taken out (its part along
        # the room directions set to the poses' mean), or the field would bend them.
        flux = flux - ((flux - flux.mean(axis=0)) @ room) @ room.T
    twists = np.array([deflection_twist(b.reshape(-1, 3), geometry, pmap) for b in flux])
    n = len(fit_set)  # with the room's no-load poses (enough to measure it) the zero is measured
    zero = (raw[n:], twists[n:]) if room is not None and len(zero_set) >= MIN_NO_LOAD_POSES else None

    def fitted(keep: np.ndarray) -> LinearFit:
        # The floor of the poses kept, as their own dataset would give it: a pose left out must
        # not move the truncation (a flux direction near the floor would flip with it).
        floor_kept = noise_floor(fit_set.flux_sem_t[keep]) if fit_set.samples_per_pose > 1 else 0.0
        return fit_linear(raw[:n][keep], twists[:n][keep], fit_set.wrench[keep], floor_kept, room, zero)

    outliers, response, found, largest = leave_out_outliers(
        dataset, fits, raw[:n], fit_set.wrench, room, lambda keep: fitted(keep).model.wrench(raw[:n])
    )
    warnings += found
    result = fitted(~outliers)
    excitation = check_excitation(fit_set.wrench[~outliers])  # an outlier's load skews the plan's shape
    weak = excitation.condition > CONDITION_WARN
    if weak:
        warnings.append(
            f"{excitation.explain()}: expect K's error along it amplified as much; {excitation.advice()}"
        )
    if result.flux_rank < 6:
        raise CalibrationError(
            f"the flux varies in only {result.flux_rank} directions above the noise floor "
            f"({result.floor_t * 1e6:.3g} uT): chips missing, saturated or not moving with the load"
        )
    check_stiffness(
        result.model.K,
        f"{dataset.where()}the fitted stiffness"
        + (
            ""
            if room is not None
            else " (the room's field was not rejected: if the sensor was turned "
            "in it, record no-load poses, docs/guide/calibration.md)"
        ),
        excitation.explain() if weak else "",
    )
    mismatch = check_chip_order(dataset, response, geometry)
    used = fit_set.select(~outliers)
    validation = dataset.select((dataset.split == "validation") & clean)
    poses = dataset.select(
        np.isin(np.arange(len(dataset)), fits[~outliers]) | ((dataset.split == "validation") & clean)
    )
    sv = singular_values_ka(result.model)
    report = {
        "fit_poses": len(used),
        "validation_poses": len(validation),
        "left_out_saturated": int(saturated.sum()),
        "samples_per_pose": dataset.samples_per_pose,
        "left_out_copies": int(copies.sum()),
        "left_out_outliers": fits[outliers].tolist(),
        "largest_pose_kept_sigma": largest,
        "chip_response_mismatch": mismatch,
        "position_map": pmap_source,
        "room_field": room_report,
        "wrench_excitation": {
            "singular_values": excitation.singular_values.tolist(),
            "condition": excitation.condition,
        },
        "flux_rank_above_floor": result.flux_rank,
        "noise_floor_ut": result.floor_t * 1e6,
        "singular_values_ka": sv,
        "isotropy": {
            "forces": sv["forces"][-1] / sv["forces"][0],
            "torques": sv["torques"][-1] / sv["torques"][0],
        },
        "fit_rmse": dict(zip(AXES, rmse(result.model, used).tolist())),
        "validation_rmse": (
            dict(zip(AXES, rmse(result.model, validation).tolist())) if len(validation) else None
        ),
        # Without a flux model (`procedure.calibrate` replaces it when there is one): the error
        # on the poses the calibration holds, each less its own reading noise.
        "error_model": error_model(  # against the estimate: a sample's sigma is asked at what it reads
            result.model.wrench(poses.flux_t) - poses.wrench,
            result.model.wrench(poses.flux_t),
            pose_noise(result.model.KA, poses),
            "poses",
        ),
        "warnings": warnings,
    }
    excluded = copies.copy()
    excluded[fits[outliers]] = True
    return CalibrationResult(result.model, pmap, report, np.abs(used.wrench).max(axis=0), excluded)
