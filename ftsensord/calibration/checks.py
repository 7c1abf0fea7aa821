"""What is wrong with a calibration dataset, found before the fit.

Each refusal (`CalibrationError`) names the file, the pose (its index in the file's
"poses"), the chip (address and index) or the axis, the figure that gave it away and the
likely cause: numbers that are no numbers, flux no chip can read or far below what the
magnets give (a unit), a dead or stuck chip, magnets facing the other way, wrenches that
do not follow the poses' own masses, lever arms and gravity (a unit, a sign), loads beyond
the sensor's range. Poses logged twice are left out with a warning.
"""

from __future__ import annotations

import math

import numpy as np

from ftsensord.calibration.dataset import AXES, AXIS_UNITS, STRONGEST_READING_MIN_T, Dataset, implausible_flux
from ftsensord.errors import CalibrationError
from ftsensord.model.fluxmodel import FluxModel
from ftsensord.model.geometry import SensorGeometry
from ftsensord.model.linear import SENSOR_RANGE
from ftsensord.sim.loads import G

#: A channel varying across the fit poses by less than this many times its mean's standard
#: error carries no load: under the plan's 50 g and 200 g loads and the room's turning
#: field every live channel moves by tens of uT (the least of the default scene's sensor1:
#: 19.7 uT, 72 standard errors), a stuck one by its noise alone (or not at all).
STUCK_FACTOR = 3.0
#: A chip's own magnet, 6 mm away, gives it about 1.5 mT: what a unit error is judged against.
OWN_MAGNET_T = 1.5e-3
#: A wrench axis is judged against the poses' masses, lever arms and gravity only on
#: poses where those give it at least this share of its largest value (the ratio of
#: two numbers near zero says nothing).
JUDGED_SHARE = 0.1
#: The recorded and the mass-given wrench may differ by this factor on an axis before the
#: axis is refused: masses and levers are known to 0.1 %, a reference sensor to a few %;
#: a unit (x 1000) or a sign (x -1) is far outside.
RATIO_LIMIT = 2.0
#: A calibration load beyond this multiple of the sensor's range (+-50 N, +-20 N, +-0.2 Nm)
#: is no calibration pose: the silicone would tear long before (judged on the median pose).
RANGE_LIMIT = 3.0


def chip_name(dataset: Dataset, index: int) -> str:
    """'chip 0x0F (index 3)': the address a user wires and the index of its columns."""
    return f"chip 0x{dataset.addresses[index]:02X} (index {index})"


def check_finite(dataset: Dataset) -> None:
    """Refuse NaN or infinite numbers, naming the first pose and key."""
    for name in ("flux_t", "flux_sem_t", "wrench", "mass_kg", "lever_m", "gravity_dir"):
        values = np.asarray(getattr(dataset, name), dtype=float).reshape(len(dataset), -1)
        bad = ~np.isfinite(values)
        if bad.any():
            k = int(np.flatnonzero(bad.any(axis=1))[0])
            raise CalibrationError(
                f"{dataset.where()}poses[{k}].{name}: {values[k][bad[k]][0]} is no number "
                f"({int(bad.any(axis=1).sum())} pose(s) hold one): a reading or a log line "
                "that failed; record the pose again or leave it out"
            )


def check_plausible(dataset: Dataset) -> None:
    """Refuse flux no MLX90393 can report, naming the chip and the pose."""
    judged = np.repeat(~dataset.saturated, 3, axis=1)  # a saturated chip's values are no readings
    for name, values in (("flux_t", dataset.flux_t), ("flux_sem_t", dataset.flux_sem_t)):
        why = implausible_flux(values, dataset.saturated)
        if why is not None:
            k, j = np.unravel_index(int(np.argmax(np.where(judged, np.abs(values), 0.0))), values.shape)
            raise CalibrationError(
                f"{dataset.where()}poses[{k}].{name}: {chip_name(dataset, int(j) // 3)} reads "
                f"{values[k, j]:.4g} on {'xyz'[j % 3]}: {why}"
            )
    for a, sweep in dataset.sweeps.items():
        why = implausible_flux(sweep.flux_t)
        if why is not None:
            raise CalibrationError(f"{dataset.where()}position_sweeps.0x{a:02X}.flux_t: {why}")


def check_flux_scale(dataset: Dataset) -> None:
    """Refuse flux far below what each chip's own magnet gives it: a unit error."""
    live = np.where(np.repeat(dataset.saturated, 3, axis=1), 0.0, np.abs(dataset.flux_t))
    strongest = float(live.max()) if live.size else 0.0
    if strongest >= STRONGEST_READING_MIN_T:
        return
    factor = 10.0 ** round(math.log10(OWN_MAGNET_T / strongest)) if strongest > 0 else math.inf
    raise CalibrationError(
        f"{dataset.where()}poses[].flux_t: the strongest reading is {strongest * 1e6:.3g} uT, far below what the "
        f"magnets and loads must produce: each chip's own magnet, 6 mm away, gives it about "
        f"{OWN_MAGNET_T * 1e3:g} mT (never below {STRONGEST_READING_MIN_T * 1e3:g} mT). A unit error: "
        f"x {factor:g} would bring it to {strongest * factor * 1e3:.3g} mT (flux is in T)"
    )


def check_chips(dataset: Dataset) -> None:
    """Refuse a chip that reads 0 throughout (dead) or does not follow the loads (stuck)."""
    rows = (dataset.split == "fit") & ~dataset.saturated.any(axis=1)
    flux, sem = dataset.flux_t[rows], dataset.flux_sem_t[rows]
    if len(flux) < 2:
        return  # nothing varies over one pose; the fit's pose count refuses it
    spread, noise = flux.std(axis=0), np.median(sem, axis=0)
    for j in range(len(dataset.addresses)):
        cols = slice(3 * j, 3 * j + 3)
        if not np.any(flux[:, cols]):
            raise CalibrationError(
                f"{dataset.where()}{chip_name(dataset, j)} reads 0 in every fit pose: dead, "
                "not powered or not connected. Check its wiring and record the dataset again"
            )
        stuck = [a for a, s, n in zip("xyz", spread[cols], noise[cols]) if s <= STUCK_FACTOR * n]
        if stuck:
            worst = float(spread[cols].min())
            raise CalibrationError(
                f"{dataset.where()}{chip_name(dataset, j)} does not follow the loads on {', '.join(stuck)}: its "
                f"reading varies by {worst * 1e6:.3g} uT across the {len(flux)} fit poses, within {STUCK_FACTOR:g}x "
                f"its noise ({float(noise[cols].min()) * 1e6:.3g} uT), where every live chip moves by tens of uT. "
                "A stuck chip or a reading repeated by the logger: check it with `ftsensord scan`"
            )


def check_polarity(dataset: Dataset, geometry: SensorGeometry) -> None:
    """Refuse chips whose mean reading points against the model's field of their magnet.

    The own magnet gives each chip about 1.5 mT, the room's field at most 0.1 mT, a chip's
    tilt turns it by degrees: measured and modelled fields are nearly parallel, or (a
    magnet turned over) nearly opposite; a negative cosine is the second."""
    model = FluxModel(geometry, geometry.magnet_moment_am2).predict(np.eye(4)).reshape(-1, 3)
    usable = ~dataset.saturated
    if not usable.any():
        return
    mean = np.array(
        [
            dataset.flux_t[usable[:, j], 3 * j : 3 * j + 3].mean(axis=0) if usable[:, j].any() else model[j]
            for j in range(len(dataset.addresses))
        ]
    )
    cos = np.einsum("ni,ni->n", mean, model) / (np.linalg.norm(mean, axis=1) * np.linalg.norm(model, axis=1))
    against = np.flatnonzero(cos < 0)
    if not len(against):
        return
    j = int(against[0])
    seen = (
        f"{chip_name(dataset, j)} reads {np.round(mean[j] * 1e3, 2).tolist()} mT where the model has "
        f"{np.round(model[j] * 1e3, 2).tolist()} mT"
    )
    if len(against) == len(cos):
        raise CalibrationError(
            f"{dataset.where()}every chip reads its magnet's field opposite to the model's ({seen}): the magnets "
            "face the other way round. The paper does not say which pole faces the chip; ftsensord's model has "
            "each magnet magnetised along its chip's z axis (the field at the chip along +z). Turn the magnets "
            "over, or check that the chips' z axes point at them"
        )
    raise CalibrationError(
        f"{dataset.where()}"
        + ", ".join(chip_name(dataset, int(i)) for i in against)
        + f" read their magnet's field opposite to the model's ({seen}), the other chips along it: those "
        "magnets were glued the other way round, or those chips mounted upside down"
    )


def check_loads(dataset: Dataset) -> None:
    """Refuse wrenches that do not follow the poses' own masses, lever arms and gravity
    (a unit or a sign per axis), and calibration loads beyond the sensor's range."""
    loaded = (dataset.split != "no-load") & (dataset.mass_kg > 0)
    if loaded.any():
        f = dataset.mass_kg[loaded, None] * G * dataset.gravity_dir[loaded]
        given = np.concatenate([f, np.cross(dataset.lever_m[loaded], f)], axis=1)
        recorded = dataset.wrench[loaded]
        ratios = _ratios(recorded, given)
        off = [k for k in range(6) if not 1 / RATIO_LIMIT <= ratios[k] <= RATIO_LIMIT]
        if off:
            for shift, word in ((1, "behind"), (-1, "ahead of")):  # a log that slipped by one pose
                pairs = (recorded[1:], given[:-1]) if shift > 0 else (recorded[:-1], given[1:])
                if len(pairs[0]) and all(1 / RATIO_LIMIT <= r <= RATIO_LIMIT for r in _ratios(*pairs)):
                    raise CalibrationError(
                        f"{dataset.where()}poses[].wrench: each recorded wrench is the one the masses, lever arms "
                        f"and gravity of the pose {'before' if shift > 0 else 'after'} give, not its own "
                        f"({', '.join(f'{AXES[k]} {ratios[k]:.3g}x' for k in off)} of its own): the wrench log "
                        f"is one pose {word} the poses (and their flux). Realign it"
                    )
            raise CalibrationError(f"{dataset.where()}poses[].wrench: " + _unit_or_sign(off, ratios))
    calibration = dataset.split != "no-load"
    over = np.abs(dataset.wrench[calibration]) / SENSOR_RANGE
    # The typical pose, not the largest: one pose beyond the range is an outlier the fit
    # leaves out and names (`screening`); most of them beyond it is a unit.
    typical = float(np.median(over.max(axis=1))) if over.size else 0.0
    if typical > RANGE_LIMIT:
        k = int(np.argsort(over.max(axis=1))[len(over) // 2])
        axis = int(np.argmax(over[k]))
        pose = int(np.flatnonzero(calibration)[k])
        raise CalibrationError(
            f"{dataset.where()}poses[{pose}].wrench: {AXES[axis]} = {dataset.wrench[pose, axis]:.4g} "
            f"{AXIS_UNITS[axis]}, {over[k, axis]:.3g}x the sensor's range ({SENSOR_RANGE[axis]:g} "
            f"{AXIS_UNITS[axis]}; mass_kg {dataset.mass_kg[pose]:.4g}), and half the poses are further: no "
            "calibration load is that large. A unit: masses in g for kg, or wrenches in mN?"
        )


def _ratios(recorded: np.ndarray, given: np.ndarray) -> list[float]:
    """Per axis, the median of recorded / given over the poses where the given is not
    near zero (`JUDGED_SHARE`); 1 where the masses give that axis nothing."""
    out = []
    for k in range(6):
        big = np.abs(given[:, k]).max()
        judged = np.abs(given[:, k]) >= JUDGED_SHARE * big
        out.append(float(np.median(recorded[judged, k] / given[judged, k])) if big > 0 else 1.0)
    return out


def _unit_or_sign(off: list[int], ratios: list[float]) -> str:
    """Words for the axes whose recorded wrench is ``ratios`` times the mass-given one."""
    named = ", ".join(f"{AXES[k]} {ratios[k]:.4g}x" for k in off)
    head = f"the recorded wrench is not the one the poses' masses, lever arms and gravity give ({named})"
    axes = ", ".join(AXES[k] for k in off)
    # Within 0.1 decades (26 %) of a factor: units differ by exact powers of 1000.
    if all(ratios[k] > 0 and abs(math.log10(ratios[k]) - 3) < 0.1 for k in off):
        if all(k >= 3 for k in off):
            return head + ": torques 1000x too large, written in N mm; the file wants N m"
        return head + f": {axes} 1000x too large, a unit (mN, N mm) where the file wants N, N m"
    if all(abs(ratios[k] + 1) < 0.1 for k in off):  # -1 within 10 %: a rig's loads are known far better
        return (
            head + f": the sign of {axes} is flipped (a frame axis reversed in the log, or a sign error in "
            "the wrench's computation)"
        )
    if all(ratios[k] == 0 for k in off):
        return head + f": {axes} recorded as 0 where the masses load them (not logged?)"
    return head + ": a unit or frame differs between the wrench and the pose's description"


def duplicate_poses(dataset: Dataset) -> tuple[np.ndarray, list[str]]:
    """Poses whose flux repeats an earlier pose's to the last digit (no two averaged
    readings do): logged twice. The mask marks the copies (the first of each is kept); a
    warning names them."""
    _, first, inverse = np.unique(dataset.flux_t, axis=0, return_index=True, return_inverse=True)
    origin = first[np.ravel(inverse)]
    copies = np.flatnonzero(origin != np.arange(len(dataset)))
    if not len(copies):
        return np.zeros(len(dataset), dtype=bool), []
    return origin != np.arange(len(dataset)), [
        f"{len(copies)} poses repeat an earlier pose's flux to the last digit, which no two averaged readings "
        f"do: logged twice (poses {_ranges(copies)} repeat poses {_ranges(origin[copies])}); the copies are "
        "left out"
    ]


def _ranges(indices: np.ndarray) -> str:
    """'3, 10-39': sorted indices written as runs."""
    out, values = [], sorted(int(i) for i in indices)
    start = prev = values[0]
    for v in [*values[1:], None]:
        if v is not None and v == prev + 1:
            prev = v
            continue
        out.append(f"{start}-{prev}" if prev > start else f"{start}")
        if v is not None:
            start = prev = v
    return ", ".join(out)


def check_stiffness(K: np.ndarray, what: str, explain: str = "") -> None:
    """Refuse a K that is not positive definite: a stiffness stores energy under any
    deflection, x^T K x > 0 (the test of the symmetric part, which a fitted, slightly
    asymmetric K is judged by; unaffected by the mixed units N/m and Nm/rad, since
    scaling the axes is a congruence, which keeps the signs of the eigenvalues).
    ``explain``: why the plan may have given it (a near-dependent plan), said first."""
    eig = np.linalg.eigvalsh(0.5 * (K + K.T))
    if eig[0] > 0:
        return
    if eig[-1] < 0:  # every deflection against its load: one sign throughout
        raise CalibrationError(
            f"{what}: K is negative definite (eigenvalues of its symmetric part {eig[0]:.3g} to {eig[-1]:.3g}): "
            "every load moved the centre piece against itself, the flux and the wrenches have opposite signs "
            "throughout. Either the magnets face the other way round (the paper does not say which pole faces "
            "the chip), or every wrench's sign is flipped (gravity_dir pointing up instead of down)"
        )
    cause = (f"{explain}. " if explain else "") + (
        "Otherwise the recorded wrenches do not match the flux: check their signs, frame and units (N, Nm in {0})"
    )
    raise CalibrationError(
        f"{what}: K is not positive definite (lowest eigenvalue of its symmetric part {eig[0]:.3g}): some "
        f"deflection would store no energy, or move against its load. {cause}"
    )
