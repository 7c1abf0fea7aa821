"""The calibration procedure end to end: a simulated run of the paper's plan, and the fits
that turn a dataset into a `Calibration` (what `ftsensord dataset` and `calibrate` do)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from ftsensord.calibration import largeloads
from ftsensord.calibration.calfile import Calibration
from ftsensord.calibration.dataset import Dataset
from ftsensord.calibration.fit import (
    AXES,
    CalibrationResult,
    RoomFieldError,
    error_model,
    fit,
    pose_noise,
    range_loads,
    room_directions,
)
from ftsensord.calibration.nlfit import FitProgress, NonlinearCalibration, fit_nonlinear, nonlinear_errors
from ftsensord.calibration.relaxation import SiliconeCalibration, dwell_loads, identify, settle_s
from ftsensord.calibration.report import format_rmse
from ftsensord.calibration.rig import record_dataset, record_hold, simulate_sweeps, simulated_robot
from ftsensord.calibration.thermal import CalibrationTemperature, thermal_fit
from ftsensord.errors import CalibrationError, ConfigError
from ftsensord.model import se3
from ftsensord.model.geometry import SensorGeometry
from ftsensord.model.linear import EXTRAPOLATION_MARGIN, LinearModel
from ftsensord.sim import PhysicalScene, default_scene, load_scene, simulated_bus
from ftsensord.sim.loads import CalibrationPose, gravity_to_down, paper_plan

#: No-load poses a dataset records by default: 24, 12 % of the 193 loaded poses' robot
#: time, twice the 12 docs/guide/calibration.md asks of a real run (so that the room field's
#: 3 directions are measured with spare poses to test that no 4th varies).
NO_LOAD_POSES = 24
#: The step-and-hold segment's mass (kg) and lever arm (m, {0}): the plan's heavier mass on
#: its off-axis arm, so the step loads forces and torques alike.
HOLD_MASS_KG, HOLD_LEVER_M = 0.2, (0.07, 0.0, 0.07)


def hold_poses() -> list[CalibrationPose]:
    """The step-and-hold segment's two poses (docs/guide/calibration.md): 200 g on the off-axis arm
    with gravity along (1, 1, 1) in {0}, then turned to the opposite: a step of twice the
    weight on every force and on Mx, Mz."""
    d = np.ones(3) / np.sqrt(3.0)
    return [CalibrationPose(g, HOLD_MASS_KG, np.array(HOLD_LEVER_M), gravity_to_down(g)) for g in (d, -d)]


def simulate_dataset(
    scene_path: str | Path | PhysicalScene | None,
    sensor_name: str,
    plan: str,
    *,
    poses: int,
    validation_poses: int,
    samples: int,
    seed: int,
    sweeps: bool = True,
    no_load_poses: int = NO_LOAD_POSES,
    check_poses: int = 0,
    hold_s: float = 0.0,
    hold_period_s: float = 0.0,
) -> Dataset:
    """Run the paper's calibration procedure (section VII-B) on a simulated sensor of a
    scene (a file, a scene already built, or None: the default scene): each pose's wrench
    applied, ``samples`` readings averaged; with ``sweeps``, each chip's position-map sweep
    too; ``check_poses`` at large loads (`largeloads`); with ``hold_s``, the step-and-hold
    segment after the poses (`hold_poses`, each held that long, read every ``hold_period_s``;
    0: as fast as the bus allows)."""
    if not hold_s >= 0 or hold_s == float("inf"):  # NaN too
        raise ConfigError(f"--hold-s: expected the seconds a step is held, 0 (none) or more, got {hold_s!r}")
    if not hold_period_s >= 0 or hold_period_s == float("inf"):  # NaN too
        raise ConfigError(
            f"--hold-period-s: expected the seconds between the hold's readings, 0 (as fast as the "
            f"bus allows) or more, got {hold_period_s!r}"
        )
    if check_poses < 0:
        raise ConfigError(f"--check-poses: expected 0 or more poses, got {check_poses}")
    if isinstance(scene_path, PhysicalScene):
        scene, scene_path = scene_path, "given"
    else:
        loaded = load_scene(scene_path) if scene_path else default_scene()
        if not isinstance(loaded, PhysicalScene):
            raise ConfigError(f'{scene_path}: a calibration dataset needs a scene of kind "sensors"')
        scene = loaded
    names = [s.name for s in scene.sensors]
    if sensor_name not in names:
        raise ConfigError(f"--sensor {sensor_name!r}: the scene's sensors are {', '.join(names)}")
    sensor = next(s for s in scene.sensors if s.name == sensor_name)
    bus = simulated_bus(scene, seed=seed)
    robot = simulated_robot(scene, sensor.name)
    ordered = paper_plan(
        plan, n_fit=poses, n_validation=validation_poses, n_no_load=no_load_poses, n_check=check_poses
    )
    dataset = record_dataset(
        bus,
        sensor.addresses,
        ordered,
        robot["apply_load"],
        turn=robot["turn"],
        samples=samples,
        serial=f"sim-{sensor.name}",
        source=f"simulated: scene {scene_path or 'default'}, sensor {sensor.name}, plan {plan}, seed {seed}",
    )
    if hold_s > 0:
        dataset.hold = record_hold(
            bus,
            sensor.addresses,
            hold_poses(),
            robot["apply_load"],
            hold_s=hold_s,
            turn=robot["turn"],
            period_s=hold_period_s,
        )
    if sweeps:
        dataset.sweeps = simulate_sweeps(
            sensor.addresses,
            SensorGeometry.ring(),
            field_model=scene.field_model,
            samples=samples,
            rng=np.random.default_rng(seed),
        )
    return dataset


def calibrate(
    dataset: Dataset,
    *,
    serial: str | None = None,
    frame: str = "sensor",
    nonlinear: bool = True,
    progress: Callable[[FitProgress], None] | None = None,
    allow_poor_fit: bool = False,
) -> tuple[Calibration, CalibrationResult]:
    """The linear fit (and, with ``nonlinear``, the flux model's) of ``dataset``, as a
    calibration file's content; its report holds the validation RMSE of each.

    A refused nonlinear fit raises (`CalibrationError`, naming its figures) and nothing
    is returned: a file with the linear part alone would let a configuration that asks
    for the nonlinear estimator fail later and far from the cause; the user chooses
    (``nonlinear=False``, or ``allow_poor_fit``)."""
    # Poses read at other temperatures are first brought to the calibration's (`thermal`).
    dataset, temperature, result, silicone, said = _fit_static(dataset)
    report = result.report
    report["silicone"] = said
    nl = None
    if nonlinear:
        used = dataset if result.excluded is None else dataset.select(~result.excluded)  # as the linear fit
        nl = fit_nonlinear(used, progress=progress, allow_poor_fit=allow_poor_fit)
        validation = used.select(used.split == "validation")
        errors = nonlinear_errors(nl, validation)
        report["nonlinear"] = {
            "gap_mm": nl.gap_m * 1e3,
            "fit_rms_residual_ut": nl.fit_rms_residual_t * 1e6,
            "warnings": list(nl.warnings),
            "validation_rmse": (
                dict(zip(AXES, np.sqrt(np.mean(errors**2, axis=0)).tolist())) if len(validation) else None
            ),
            "error_model": nonlinear_error_model(nl, used, result.model, result.wrench_range),
        }
        # The linear map's error over the calibration's range, read through the flux model.
        report["error_model"] = linear_error_model(result.model, nl, result.wrench_range)
    report["large_loads"], found = largeloads.judge(
        dataset if result.excluded is None else dataset.select(~result.excluded), result.model, nl
    )
    if nl is not None:
        nl.warnings += tuple(found)
        report["nonlinear"]["warnings"] += found
    cal = Calibration(
        result.model,
        dataset.addresses,
        serial or dataset.serial,
        frame,
        result.position_map,
        report,
        nl,
        result.wrench_range,
        temperature,
        silicone,
    )
    return cal, result


def linear_error_model(
    linear: LinearModel, nl: NonlinearCalibration, wrench_range: np.ndarray
) -> dict[str, Any] | None:
    """The linear map's error (`fit.error_model`) at `fit.range_loads` within ``wrench_range``,
    each load's flux predicted by the calibration's flux model and the map tared on its no-load
    flux, as the daemon's tare does.

    Why not the poses' own errors: the plan hangs each mass on one of its arms, so its forces
    come with the torques of those arms, and K A is fitted to make its error small there. A
    force with another torque (a push near the flange, a couple) is off the plan, and there the
    map's error is larger (docs/results/axis-gain.md: with the four long arms alone a pure Fy
    read 10 % low, the poses showing none of it). The flux model reproduces the part's flux
    within its 0.4 uT residual over the whole range (its estimate's error there is 0.1-0.2 %
    of the load), so it tells the map's error at any load of the range to a few mN; the poses
    cannot. Beyond the range the linear estimate is flagged `extrapolated`."""
    estimator = nl.estimator()
    loads = range_loads(wrench_range)

    def flux(w: np.ndarray) -> np.ndarray:
        xi = nl.zero_twist + np.linalg.solve(nl.K, w)
        return estimator.model.predict(se3.exp_se3(xi))

    zero = linear.with_zero(flux(np.zeros(6)))
    estimates = np.array([zero.wrench(flux(w)) for w in loads])
    # Against the estimate, not the load: a sample's sigma is asked at the wrench it reads.
    return error_model(estimates - loads, estimates, 0.0, "flux model", tared=True)


def nonlinear_error_model(
    nl: NonlinearCalibration, used: Dataset, linear: LinearModel, wrench_range: np.ndarray
) -> dict[str, Any] | None:
    """The nonlinear estimate's error (`fit.error_model`) on the poses the fit kept, the
    validation poses, and the check poses (kilograms, far beyond ``wrench_range``: they set how
    the error grows beyond the calibration's range, the form's last term, from 1.5 times it), each less its reading
    noise (through K A: the solve's is within a few % of it); poses whose solve did not converge
    are left out."""
    poses = used.select(np.isin(used.split, ["fit", "validation", "check"]) & ~used.saturated.any(axis=1))
    estimator = nl.estimator()
    estimates = [estimator.estimate(b) for b in poses.flux_t]
    ok = np.array([e.converged for e in estimates], dtype=bool)
    read = np.array([nl.wrench(e.xi) for e in estimates]).reshape(-1, 6)
    # Against the estimate, not the load: a sample's sigma is asked at the wrench it reads. The
    # range's form holds to EXTRAPOLATION_MARGIN x the fit poses' loads, where a linear estimate
    # is flagged: the validation poses reach a little past the fit's own (a few are), the
    # check poses 5-20 times.
    return error_model(
        read[ok] - poses.wrench[ok],
        read[ok],
        pose_noise(linear.KA, poses)[ok],
        "poses",
        EXTRAPOLATION_MARGIN * np.asarray(wrench_range, dtype=float),
        poses.wrench[ok],
    )


def _fit_static(
    raw: Dataset,
) -> tuple[Dataset, CalibrationTemperature | None, CalibrationResult, SiliconeCalibration | None, str]:
    """The linear fit (`thermal_fit`), and the silicone's series from the step-and-hold: the
    dataset as fitted, its temperature, the fit, the series (None: not identified) and the
    report's line on it. With the poses' times, the fit is made again on the loads the
    silicone carried over each dwell (`dwell_loads`), and so is what follows it."""
    try:
        dataset, temperature, result = thermal_fit(raw, fit)
    except RoomFieldError as exc:
        if exc.after_load_s is None:  # no load before the no-load poses: no after-effect in them
            raise
        raise _after_effect(raw, exc) from exc
    if raw.hold is None:
        return (
            dataset,
            temperature,
            result,
            None,
            (
                "not identified: the dataset has no step-and-hold segment "
                "(docs/guide/calibration.md); the daemon runs without creep compensation"
            ),
        )
    silicone, said = identify(raw.hold, result.model.wrench)
    if silicone is None:
        return dataset, temperature, result, None, said
    if raw.times_s is None:
        return (
            dataset,
            temperature,
            result,
            silicone,
            said
            + (
                "; the poses' times were not recorded: K fitted on the dwells' creeping averages, "
                "read through the scale "
                "(the nonlinear estimator's own differs by 1-2 %: docs/guide/calibration.md)"
            ),
        )
    # A dwell's average holds creep that depends on the poses before it. Fitted as a static load, K
    # is neither the instantaneous nor the long-term stiffness but each model's own mix: on the
    # default scene's part the nonlinear one read a long-held 2 N Fx 1 % higher than the linear one,
    # with 3-5 % on Fy and Fz. Fitted on the load the silicone carried, both K are the long-term one.
    carried = replace(
        raw, wrench=dwell_loads(silicone.relaxation, raw.wrench, raw.times_s, raw.samples_per_pose)
    )
    dataset, temperature, result = thermal_fit(carried, fit)
    again, said = identify(raw.hold, result.model.wrench)  # the series again; the scale now near 1
    if again is None:  # K is now the long-term stiffness, and nothing undoes the creep
        said += (
            "; K is the long-term stiffness, so without the series a changing load reads low "
            "until the silicone settles"
        )
    return (
        dataset,
        temperature,
        result,
        again,
        f"fitted on the loads the silicone carried over each dwell; {said}",
    )


def _after_effect(raw: Dataset, exc: RoomFieldError) -> CalibrationError:
    """The no-load check's refusal of a dataset whose no-load poses followed a load, judged:
    when the dataset's step-and-hold gives the silicone's series and the after-effect it
    computes for those poses (`dwell_loads`) explains the extra directions (taken out, the
    no-load poses vary in 3, as a uniform field does), the refusal names it and the time the
    silicone needs; when it does not explain them, today's refusal as it was; without a
    step-and-hold, today's refusal and what the dataset cannot tell."""
    wait = f"{exc.after_load_s:.3g} s after a load came off"
    if raw.hold is None or raw.times_s is None:
        return CalibrationError(
            f"{exc}. Or, as the no-load poses were recorded {wait}, a silicone's after-effect: this dataset has no "
            "step-and-hold segment to tell its creep by. Record the no-load poses first, before any load, and a "
            "step-and-hold segment (docs/guide/calibration.md)"
        )
    try:  # a first fit that takes the room's directions from the geometry: the series from the hold
        dataset, _, first = thermal_fit(raw, partial(fit, room_field="geometry"))
    except CalibrationError:
        return exc  # no fit to judge the after-effect by: the refusal as it stands
    silicone, _ = identify(raw.hold, first.model.wrench)
    if silicone is None:
        return exc
    model, relaxation = first.model, silicone.relaxation
    no_load = dataset.split == "no-load"
    declared = np.where(no_load[:, None], 0.0, raw.wrench)  # a no-load pose carries none by its split
    carried = dwell_loads(relaxation, declared, raw.times_s, raw.samples_per_pose)
    # The flux of what each no-load pose still carried: b - b0 = H xi, xi = K^-1 w (`LinearModel`).
    after = (model.H @ np.linalg.solve(model.K, carried[no_load].T)).T
    flux = dataset.flux_t.copy()
    flux[no_load] -= after
    try:
        room_directions(replace(dataset, flux_t=flux), SensorGeometry.ring(), "measured")
    except CalibrationError:
        return exc  # the after-effect is not what varies: a rod, a mass or a field, as it says
    # How long the silicone needs: until the largest load's after-effect is under a pose's noise.
    loads = (model.H @ np.linalg.solve(model.K, raw.wrench[~no_load].T)).T
    noise = float(np.median(dataset.flux_sem_t[no_load])) * np.sqrt(flux.shape[1])
    largest = float(np.linalg.norm(loads, axis=1).max())
    need = settle_s(relaxation, noise / largest)
    return CalibrationError(
        f"{raw.where()}the no-load poses carry the after-effect of the loads before them (the silicone's creep): "
        f"recorded {wait}, they vary in more than 3 flux directions ({exc.figures}), and with the "
        "after-effect the dataset's step-and-hold gives (relaxation "
        f"{[[round(g, 3), round(t, 3)] for g, t in relaxation.pairs()]}, fraction and s) taken out, in 3, as the "
        f"room's uniform field does. This silicone needs {need:.0f} s after its largest load comes off before what "
        f"it carries is under a no-load pose's noise: record the no-load poses first, before any load touches the "
        f"sensor, or wait that long after the last load comes off (docs/guide/calibration.md)"
    )


def summary(cal: Calibration) -> str:
    """What `ftsensord calibrate` prints: poses used, RMSE per axis, singular values of K A."""
    report = cal.report
    sv, iso = report["singular_values_ka"], report["isotropy"]
    lines = [f"WARNING: {w}" for w in warnings(cal)]
    lines.append(
        f"fit on {report['fit_poses']} poses ({report['left_out_saturated']} left out: saturated), "
        f"validated on {report['validation_poses']}"
    )
    if report["validation_rmse"]:
        lines.append("validation RMSE: " + format_rmse(report["validation_rmse"]))
    lines.append("fit RMSE:        " + format_rmse(report["fit_rmse"]))
    if cal.nonlinear is not None and report["nonlinear"]["validation_rmse"]:
        lines.append(
            f"nonlinear (residual {cal.nonlinear.fit_rms_residual_t * 1e6:.2f} uT) validation RMSE: "
            + format_rmse(report["nonlinear"]["validation_rmse"])
        )
    large = report.get("large_loads")
    if large is not None:
        lines.append(
            f"large loads ({large['poses']} check poses, |F| to {large['largest_force_n']:.3g} N) RMSE: "
            f"linear {format_rmse(list(large['linear_rmse'].values()))}"
            + (
                f"; nonlinear {format_rmse(list(large['nonlinear_rmse'].values()))}"
                if large.get("nonlinear_rmse")
                else ""
            )
        )
    else:
        lines.append(largeloads.NOT_JUDGED)
    if cal.silicone is not None:
        lines.append(
            f"silicone: relaxation {cal.silicone.relaxation.pairs()} (fraction, s), scale "
            f"{cal.silicone.scale:.4g}: the daemon undoes its creep"
        )
    elif isinstance(report.get("silicone"), str):  # why it was not identified
        lines.append(f"silicone: {report['silicone']}")
    if cal.nonlinear is None:  # the part is judged by the nonlinear fit: say that it was not
        lines.append(
            "nonlinear fit skipped: the part's departures from the model (silicone that stiffens, "
            "a field it lacks) were not judged"
        )
    lines.append(
        f"sigma(KA): forces {sv['forces'][0]:.3g}..{sv['forces'][-1]:.3g} N/uT (isotropy {iso['forces']:.2f}), "
        f"torques {sv['torques'][0]:.3g}..{sv['torques'][-1]:.3g} Nm/uT (isotropy {iso['torques']:.2f})"
    )
    return "\n".join(lines)


def warnings(cal: Calibration) -> list[str]:
    """Every warning a calibration was written with: the data's (the linear fit's) and the
    nonlinear model's (kept against its refusal, or departing from the part)."""
    nonlinear = cal.report.get("nonlinear") or {}
    return list(cal.report.get("warnings", [])) + list(nonlinear.get("warnings", []))
