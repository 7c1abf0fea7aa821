"""Pathological calibration datasets: is each refused or warned, with its cause named?

Made from a real dataset of the project's own procedure (`simulate_dataset`: the default
scene's as-built sensor1 in the Earth's field, the six-axis plan, as `ftsensord dataset`
records it), then spoilt one way per kind: what a logging script, a unit, a wiring or a
hand-made part gets wrong. A few kinds are the part itself built wrong (magnets facing the
other way or glued tilted, silicone that stiffens): those are recorded again on the scene
with that change. Each goes through `ftsensord calibrate` (file written, read back, fitted)
as a user's would. Outcomes: "refused" (exit 2, no file), "warned" (a file written, with a
warning naming the cause), "silent" (a file written without a word: a failure of the checks
when the data are spoilt). Where a file is written, its linear model's validation RMSE on
the clean dataset's validation poses (the part's own, for a part recorded again) is given
against the clean fit's.

    python -m benchmarks.robustness.pathological            # the table in docs/guide/calibration.md (~2 min)
    python -m benchmarks.robustness.pathological --quick    # a handful of kinds on a small dataset (a test)
"""

from __future__ import annotations

import argparse
import contextlib
import io
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from benchmarks.common import tilted
from ftsensord.calibration.calfile import Calibration
from ftsensord.calibration.dataset import Dataset
from ftsensord.calibration.fit import rmse
from ftsensord.calibration.nlfit import nonlinear_rmse
from ftsensord.calibration.procedure import simulate_dataset
from ftsensord.chip.mlx90393 import HALL_SATURATION_T
from ftsensord.cli import main as ftsensord
from ftsensord.model import se3
from ftsensord.model.linear import SENSOR_RANGE
from ftsensord.sim import PhysicalScene, SimSensor, default_scene
from ftsensord.sim.loads import FixedOrientation, StaticLoad

#: The pose spoilt where a kind spoils one, and the chips. POSE: a 200 g fit pose on the arm (-0.05,
#: -0.05, 0.05) after the no-load poses the plan records first (24 in the full run: its fit pose 7;
#: 12 quick: fit pose 19, the same mass and arm).
POSE, CHIP, OTHER_CHIP = 31, 3, 5


@dataclass
class Source:
    """The clean dataset, and the same plan recorded again on a part built differently."""

    clean: Dataset
    size: dict[str, int]
    #: The part the last kind recorded again was built as (None: the default scene's).
    scene: PhysicalScene | None = None

    def record(self, build: Callable[[SimSensor], None]) -> Dataset:
        """The plan recorded on the default scene with its sensor1 changed by ``build``."""
        self.scene = default_scene()
        build(self.scene.sensors[0])
        return simulate_dataset(self.scene, "sensor1", "six-axis", seed=0, **self.size)  # type: ignore[arg-type]


def copy(ds: Dataset, **arrays: np.ndarray) -> Dataset:
    """``ds`` with its arrays copied (so a kind can spoil them in place), some replaced."""
    fresh = {k: v.copy() for k, v in ds.__dict__.items() if isinstance(v, np.ndarray)}
    return replace(ds, **{**fresh, **arrays})


def fit_rows(ds: Dataset) -> np.ndarray:
    return np.flatnonzero(ds.split == "fit")


def _mass_20x(src: Source) -> Dataset:
    ds = copy(src.clean)
    ds.mass_kg[POSE] *= 20
    ds.wrench[POSE] *= 20
    return ds


def _flux_scaled(factor: float) -> Callable[[Source], Dataset]:
    def make(src: Source) -> Dataset:
        ds = copy(src.clean, flux_t=src.clean.flux_t * factor, flux_sem_t=src.clean.flux_sem_t * factor)
        ds.sweeps = {a: replace(s, flux_t=s.flux_t * factor) for a, s in ds.sweeps.items()}
        return ds

    return make


def _dead_chip(src: Source) -> Dataset:
    ds = copy(src.clean)
    ds.flux_t[:, 3 * CHIP : 3 * CHIP + 3] = 0.0
    ds.flux_sem_t[:, 3 * CHIP : 3 * CHIP + 3] = 0.0
    return ds


def _stuck_chip(src: Source) -> Dataset:
    ds = copy(src.clean)
    ds.flux_t[:, 3 * CHIP : 3 * CHIP + 3] = ds.flux_t[0, 3 * CHIP : 3 * CHIP + 3]  # the first reading, held
    return ds


def _stuck_channel(src: Source) -> Dataset:
    ds = copy(src.clean)
    ds.flux_t[:, 3 * CHIP + 2] = ds.flux_t[0, 3 * CHIP + 2]
    return ds


def _chip_off_in_one_pose(src: Source) -> Dataset:
    ds = copy(src.clean)
    ds.flux_t[POSE, 3 * OTHER_CHIP + 2] += 2e-3
    return ds


def _swapped_chips(src: Source) -> Dataset:
    ds = copy(src.clean)
    a, b = slice(3 * CHIP, 3 * CHIP + 3), slice(3 * OTHER_CHIP, 3 * OTHER_CHIP + 3)
    for arr in (ds.flux_t, ds.flux_sem_t):
        arr[:, a], arr[:, b] = arr[:, b].copy(), arr[:, a].copy()
    return ds


def _torques_nmm(src: Source) -> Dataset:
    ds = copy(src.clean)
    ds.wrench[:, 3:] *= 1e3
    return ds


def _masses_in_grams(src: Source) -> Dataset:
    ds = copy(src.clean)
    ds.mass_kg *= 1e3
    ds.wrench *= 1e3
    return ds


def _sign_flip(src: Source) -> Dataset:
    ds = copy(src.clean)
    ds.wrench[:, 1] *= -1
    return ds


def _gravity_up(src: Source) -> Dataset:
    ds = copy(src.clean)
    ds.wrench *= -1
    ds.gravity_dir *= -1
    ds.rotation = None  # the robot's rotations would contradict the flipped gravity (refused on load)
    return ds


def _shifted_wrenches(src: Source) -> Dataset:
    ds = copy(src.clean)
    rows = fit_rows(ds)
    ds.wrench[rows] = np.roll(ds.wrench[rows], 1, axis=0)  # the log one pose behind the flux
    return ds


def _duplicated(src: Source) -> Dataset:
    ds = src.clean
    order = np.concatenate([np.arange(len(ds)), fit_rows(ds)[10:40]])  # 30 fit poses logged twice
    return copy(ds.select(order))


def _nan_row(src: Source) -> Dataset:
    ds = copy(src.clean)
    ds.flux_t[POSE] = np.nan
    return ds


def _inf_wrench(src: Source) -> Dataset:
    ds = copy(src.clean)
    ds.wrench[POSE, 2] = np.inf
    return ds


def _too_few(src: Source) -> Dataset:
    ds = src.clean
    keep = np.ones(len(ds), dtype=bool)
    keep[fit_rows(ds)[20:]] = False
    return copy(ds.select(keep))


def _one_arm(src: Source) -> Dataset:
    ds = src.clean
    arm = ds.lever_m[fit_rows(ds)[0]]
    keep = (ds.split != "fit") | np.all(ds.lever_m == arm, axis=1)
    return copy(ds.select(keep))


def _near_collinear(src: Source) -> Dataset:
    """One lever arm, and a handful of poses on the others: every axis varies, barely independently."""
    ds = src.clean
    rows = fit_rows(ds)
    arm = ds.lever_m[rows[0]]
    others = [k for k in rows if not np.all(ds.lever_m[k] == arm)]
    keep = (ds.split != "fit") | np.all(ds.lever_m == arm, axis=1)
    keep[others[:3]] = True
    return copy(ds.select(keep))


def _degrees(src: Source) -> Dataset:
    ds = copy(src.clean)
    assert ds.rotation is not None
    ds.rotation = np.array([se3.exp_so3(np.degrees(se3.log_so3(R))) for R in ds.rotation])
    return ds


def _magnets(change: Callable[[np.ndarray, np.random.Generator], np.ndarray]) -> Callable[[Source], Dataset]:
    def make(src: Source) -> Dataset:
        def build(sensor: SimSensor) -> None:
            g = sensor.geometry
            sensor.geometry = replace(g, magnet_axis=change(g.magnet_axis, np.random.default_rng(5)))

        return src.record(build)

    return make


def _reversed(axis: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    return -axis


def _stiffening(src: Source) -> Dataset:
    def build(sensor: SimSensor) -> None:
        sensor.stiffening = 0.3

    return src.record(build)


#: kind: (what was done, how).
KINDS: dict[str, tuple[str, Callable[[Source], Dataset]]] = {
    "clean": ("nothing (the control)", lambda src: src.clean),
    "mass-20x": (f"pose {POSE}'s mass (and wrench) logged 20x", _mass_20x),
    "flux-1000x-small": ("all flux 1000x too small", _flux_scaled(1e-3)),
    "flux-in-mT": ("all flux written in mT (1000x too large)", _flux_scaled(1e3)),
    "dead-chip": (f"chip {CHIP} reads 0 in every pose", _dead_chip),
    "stuck-chip": (f"chip {CHIP} repeats its first reading in every pose", _stuck_chip),
    "stuck-channel": (f"chip {CHIP}'s z repeats its first reading", _stuck_channel),
    "chip-2mT-one-pose": (f"chip {OTHER_CHIP} 2 mT off (z) in pose {POSE}", _chip_off_in_one_pose),
    "swapped-chips": (f"chips {CHIP} and {OTHER_CHIP} swapped in the flux columns", _swapped_chips),
    "torques-in-Nmm": ("torques in N mm", _torques_nmm),
    "masses-in-g": ("masses (and wrenches) in g for kg", _masses_in_grams),
    "sign-flip-Fy": ("Fy's sign flipped", _sign_flip),
    "gravity-up": ("gravity taken upwards: every wrench's sign flipped", _gravity_up),
    "wrench-one-pose-behind": ("the fit poses' wrenches one pose behind their flux", _shifted_wrenches),
    "duplicated-poses": ("30 fit poses logged twice", _duplicated),
    "nan-row": (f"pose {POSE}'s flux NaN", _nan_row),
    "inf-wrench": (f"pose {POSE}'s Fz infinite", _inf_wrench),
    "too-few-poses": ("20 fit poses", _too_few),
    "one-arm-plan": ("the fit poses of one lever arm only", _one_arm),
    "near-collinear-plan": ("one lever arm and 3 poses on the others", _near_collinear),
    "rotation-degrees": ("rotations built from angles in degrees taken as radians", _degrees),
    "magnets-reversed": ("all magnets facing the other way (recorded again)", _magnets(_reversed)),
    "magnets-tilted": ("magnets glued 2-7 deg tilted (recorded again)", _magnets(tilted)),
    "silicone-stiffening": ("silicone 30 % stiffer at range (recorded again)", _stiffening),
}
#: The quick mode's kinds: a few of each outcome's causes, all made without recording again.
QUICK = (
    "clean",
    "mass-20x",
    "flux-1000x-small",
    "dead-chip",
    "chip-2mT-one-pose",
    "torques-in-Nmm",
    "swapped-chips",
)


@dataclass
class Outcome:
    """What `ftsensord calibrate` did with one kind: "refused", "warned" or "silent", the
    message (the refusal, or the warnings), the same with ``--linear-only``, and where a
    file was written its validation RMSE, worst axis, as a multiple of the clean fit's
    (linear; nonlinear where fitted), and its error on large loads of the part (`large_loads`)."""

    kind: str
    what: str
    outcome: str
    message: str
    linear_only: str
    validation: str
    large: str = ""


def calibrate(path: Path, out: Path, *options: str) -> tuple[int, str, str]:
    """`ftsensord calibrate` in-process: its exit status, stdout and stderr (progress left out)."""
    stdout, stderr = io.StringIO(), io.StringIO()
    if out.exists():
        out.unlink()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        code = ftsensord(["calibrate", str(path), "-o", str(out), *options])
    errors = "\n".join(
        line for line in stderr.getvalue().splitlines() if "nonlinear fit: iteration" not in line
    )
    assert code == 0 or not out.exists(), f"{path}: refused, yet {out} was written"
    return code, stdout.getvalue(), errors


def classify(code: int, stdout: str, stderr: str) -> tuple[str, str]:
    """("refused" | "warned" | "silent", the refusal's or the warnings' text)."""
    if code != 0:
        return "refused", stderr.removeprefix("ftsensord: ").split("\nNo file written")[0].strip()
    warnings = [
        line.removeprefix("WARNING: ") for line in stdout.splitlines() if line.startswith("WARNING: ")
    ]
    return ("warned", " / ".join(warnings)) if warnings else ("silent", "")


def judge(
    kind: str,
    src: Source,
    work: Path,
    baseline: dict[str, np.ndarray],
    options: tuple[str, ...],
    large_count: int,
) -> Outcome:
    what, make = KINDS[kind]
    ds = make(src)
    path, out = work / f"{kind}.json", work / f"{kind}-cal.json"
    ds.save(path)
    outcome, message = classify(*calibrate(path, out, *options))
    message = message.replace(f"{work}/", "")  # the temporary folder: noise in a table
    validation = large = ""
    if outcome != "refused":
        # A part recorded again is judged on its own validation poses; a spoilt file on the clean ones.
        truth = ds if kind in RECORDED else src.clean
        val = truth.select(truth.split == "validation")
        cal = Calibration.load(out)
        lin = float(np.max(rmse(cal.model, val) / baseline["linear"]))
        validation = f"linear {lin:.2f}x"
        if cal.nonlinear is not None:
            nl = float(np.max(nonlinear_rmse(cal.nonlinear, val) / baseline["nonlinear"]))
            validation += f", nonlinear {nl:.2f}x"
        if large_count:
            scene = src.scene if kind in RECORDED and src.scene is not None else default_scene()
            large = large_loads(cal, scene, large_count)
    lin_outcome = outcome if options == LINEAR_ONLY else classify(*calibrate(path, out, *LINEAR_ONLY))[0]
    return Outcome(kind, what, outcome, message, lin_outcome, validation, large)


#: The quick mode calibrates with the linear fit alone: every check of the data is made
#: there, and the nonlinear fit of a small noisy dataset takes 5-10 s (the full mode runs both).
LINEAR_ONLY = ("--linear-only",)


#: Large loads each written file is judged on in the full mode (none in the quick one).
LARGE_LOADS = 100
#: The kinds that record the plan again on a part built differently.
RECORDED = ("magnets-reversed", "magnets-tilted", "silicone-stiffening")


def source(quick: bool) -> Source:
    """The real dataset (the default scene's sensor1 as `ftsensord dataset` records it, its
    check poses at large loads included), smaller in the quick mode (none there: the linear
    fit alone judges nothing at large loads)."""
    size = (
        dict(poses=60, validation_poses=20, samples=4, no_load_poses=12)
        if quick
        else dict(poses=193, validation_poses=60, samples=100, no_load_poses=24, check_poses=24)
    )
    return Source(simulate_dataset(None, "sensor1", "six-axis", seed=0, **size), size)  # type: ignore[arg-type]


def large_loads(cal: Calibration, scene: PhysicalScene, count: int) -> str:
    """RMS |F| and |M| error of a written calibration on ``count`` large loads of the
    part it stands for (as benchmarks/accuracy/accuracy.py's: |F| 10-50 N, torques to the range,
    each at a random orientation in the room; the exact field, no noise), linear and
    nonlinear (a fall-back takes the linear estimate, as the daemon does); loads that
    saturate a chip are counted and left out."""
    rng = np.random.default_rng(1000)
    estimator = cal.nonlinear.estimator() if cal.nonlinear is not None else None
    errors: dict[str, list[np.ndarray]] = {"linear": [], "nonlinear": []}
    fell = saturated = 0
    for _ in range(count):
        w = rng.uniform(-1, 1, 6)
        f = w[:3] / np.linalg.norm(w[:3]) * rng.uniform(10, 50)
        w = np.concatenate([np.clip(f, -SENSOR_RANGE[:3], SENSOR_RANGE[:3]), w[3:] * SENSOR_RANGE[3:]])
        scene.set_load("sensor1", StaticLoad(w))
        scene.set_orientation("sensor1", FixedOrientation(se3.exp_so3(rng.normal(0, 1, 3) * np.pi)))
        b = np.concatenate([scene.field_t(a, 0.0) for a in cal.addresses])
        if np.any(
            np.abs(b) >= HALL_SATURATION_T
        ):  # a chip would clip: the daemon's degraded mode, not judged here
            saturated += 1
            continue
        linear = cal.model.wrench(b)
        errors["linear"].append(linear - w)
        if cal.nonlinear is not None and estimator is not None:
            e = estimator.estimate(b)
            fell += not e.converged
            errors["nonlinear"].append((cal.nonlinear.wrench(e.xi) if e.converged else linear) - w)
    out = []
    for name, err in errors.items():
        if err:
            e = np.array(err)
            out.append(
                f"{name} {np.sqrt(np.mean(np.sum(e[:, :3] ** 2, axis=1))):.3g} N, "
                f"{1e3 * np.sqrt(np.mean(np.sum(e[:, 3:] ** 2, axis=1))):.3g} mNm"
            )
    used = count - saturated
    return (
        "; ".join(out)
        + (f" ({fell} of {used} fell back)" if estimator is not None else "")
        + (f"; {saturated} left out, a chip saturated" if saturated else "")
    )


def render(outcomes: list[Outcome], command: str, elapsed: float, samples: str) -> str:
    rows = [
        "| kind | what was done | outcome | `--linear-only` | message | validation RMSE if written "
        "(worst axis / clean fit's) | large loads if written (RMS error) |",
        "|---|---|---|---|---|---|---|",
    ]
    for o in outcomes:
        rows.append(
            f"| {o.kind} | {o.what} | {o.outcome} | {o.linear_only} | {o.message.replace('|', '/')} | "
            f"{o.validation or '-'} | {o.large or '-'} |"
        )
    counts = {k: sum(o.outcome == k for o in outcomes[1:]) for k in ("refused", "warned", "silent")}
    head = (
        f"Command: `{command}`; {elapsed:.0f} s. {samples}. {len(outcomes) - 1} pathological kinds and the "
        f"clean control: {counts['refused']} refused, {counts['warned']} warned, {counts['silent']} silent."
    )
    return head + "\n\n" + "\n".join(rows) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help=f"only {', '.join(QUICK)}, on a small dataset")
    args = parser.parse_args(argv)
    start = time.monotonic()
    src = source(args.quick)
    kinds = QUICK if args.quick else tuple(KINDS)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        options = LINEAR_ONLY if args.quick else ()
        clean = calibrate_clean(src, work, options)
        outcomes = [judge(k, src, work, clean, options, 0 if args.quick else LARGE_LOADS) for k in kinds]
    samples = (
        f"Source: {len(src.clean)} poses ({int((src.clean.split == 'fit').sum())} fit, "
        f"{int((src.clean.split == 'validation').sum())} validation, "
        f"{int((src.clean.split == 'no-load').sum())} no-load, {int((src.clean.split == 'check').sum())} check), "
        f"{src.clean.samples_per_pose} readings a pose"
    )
    samples += (
        "; calibrated with `--linear-only`" if args.quick else "; calibrated as `ftsensord calibrate` does"
    )
    samples += (
        f". The clean fit: its largest pose kept at {float(clean['sigma']):.2g} sigma (outliers: beyond 8), "
        f"its chips' responses at most {100 * float(clean['mismatch']):.0f} % off the model's (refused: beyond "
        f"60), its plan's condition number {float(clean['condition']):.3g} (warned: above 150)"
        + (
            f", its nonlinear residual {float(clean['residual']):.2g}x the noise (warned: above 2)"
            if "residual" in clean
            else ""
        )
    )
    print(
        render(
            outcomes,
            "python -m benchmarks.robustness.pathological" + (" --quick" if args.quick else ""),
            time.monotonic() - start,
            samples,
        )
    )
    return 0 if all(o.outcome != "silent" for o in outcomes[1:]) else 1


def calibrate_clean(src: Source, work: Path, options: tuple[str, ...]) -> dict[str, np.ndarray]:
    """The clean fit's validation RMSE per axis, linear (and nonlinear, when fitted): what
    each written file is judged against."""
    path, out = work / "clean-source.json", work / "clean-source-cal.json"
    src.clean.save(path)
    code, _, errors = calibrate(path, out, *options)
    assert code == 0, errors
    cal = Calibration.load(out)
    val = src.clean.select(src.clean.split == "validation")
    figures = {
        "sigma": cal.report["largest_pose_kept_sigma"],
        "mismatch": cal.report["chip_response_mismatch"],
        "condition": cal.report["wrench_excitation"]["condition"],
    }
    if cal.nonlinear is not None:
        figures["residual"] = cal.nonlinear.fit_rms_residual_t / float(np.median(src.clean.flux_sem_t))
    return {
        "linear": rmse(cal.model, val),
        **{k: np.array(v) for k, v in figures.items()},
        **({} if cal.nonlinear is None else {"nonlinear": nonlinear_rmse(cal.nonlinear, val)}),
    }


if __name__ == "__main__":
    sys.exit(main())
