"""The silicone's memory, end to end: writes docs/results/silicone-figures.md (and docs/results/silicone.png).

A part of the default scene whose silicone relaxes (the default Prony series,
`ftsensord.sim.memory.DEFAULT_RELAXATION`) is calibrated by the simulated procedure with
its step-and-hold segment (the series identified from it); then the daemon, in process on a
virtual clock at the loop's rate, publishes sensor1's wrench under moving loads, with the
compensation (`processing.creep`) and without, against the scene's truth:

- a 2 N step on Fx held 30 s: the largest error from 0.5 s after the step on, and the time
  to half the step (the response's lag);
- sinusoids of 2 N on Fx at 0.5, 1, 2 and 5 Hz: amplitude and lag of the published wrench
  (a sine and cosine fitted over whole periods);
- a training-like profile (a tool pressed and dragged: forces of 0.5-3 N moving at 0.3-3 Hz
  on all three axes, 20 s): RMSE;
- the 100 g validation poses of the calibration (held 1 s each, as the robot does) through
  the daemon: RMSE of each pose's mean, against Table II;
- at the loop settings of docs/results/tradeoff.md: the default (burst, OSR/DIG_FILT of
  ftsensord/data/sim.toml, 100 Hz), a faster one (OSR 0, DIG_FILT 2, 140 Hz) and the default
  averaged over 4 readings.

At the default loop, each figure is given beside the same run on the same part with a perfect
spring (no memory) and the packaged calibration fitted on it: what the part does without its
memory. Cost: the stage's time per sample
and the scene's per simulated second with and without the memory.

    python -m benchmarks.accuracy.creep           # the docs' figures (about 10 minutes)
    python -m benchmarks.accuracy.creep --quick --out DIR  # CI (python -m benchmarks regenerate --quick): small
"""

from __future__ import annotations

import argparse
import contextlib
import io
import math
import sys
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from benchmarks.common import RESULTS, Capture
from ftsensord import cli
from ftsensord.acquire.health import stuck_cycles_for
from ftsensord.calibration.calfile import Calibration
from ftsensord.calibration.dataset import Dataset
from ftsensord.config.file import Config, builtin_path, load_config
from ftsensord.daemon.daemon import Daemon
from ftsensord.model.viscoelastic import CreepInverse, Relaxation
from ftsensord.processing.creep import CreepCompensation
from ftsensord.protocol import wire
from ftsensord.sim import PhysicalScene, VirtualClock, load_scene, simulated_bus
from ftsensord.sim.loads import StepLoad
from ftsensord.sim.memory import DEFAULT_RELAXATION
from ftsensord.sim.scene import default_scene_path

DOCS = RESULTS
Series = tuple[tuple[float, float], ...]
#: The quick mode's series (CI): one that creeps more and sooner than the default (the series
#: used before the default was fitted to a published loss), so that a short hold identifies it
#: and a short run shows what the compensation takes out; the full run takes the default.
HARSH: Series = ((0.10, 1.0), (0.05, 30.0))
#: The paper's Table II (N x3, Nm x3): the 100 g validation's RMSE.
TABLE_II = np.array([0.2338, 0.1136, 0.3775, 4.1e-3, 10.6e-3, 8.5e-3])
STEP_N, FREQUENCIES_HZ = 2.0, (0.5, 1.0, 2.0, 5.0)


#: The as-built parts calibrated (sensor1's tolerance seed in the default scene): seeds no other
#: test or benchmark draws, so that nothing here was tuned on them.
PARTS = (71, 72, 73)


def scene_text(memory: bool, seed: int = 1, series: Series = DEFAULT_RELAXATION) -> str:
    """The default scene (the Earth's field: a room), sensor1 the as-built part of ``seed``, its
    silicone with ``series`` when ``memory``: one line a user adds (two for another series)."""
    text = default_scene_path().read_text()
    marker = "seed = 1                        # this part; another seed is another sensor\n"
    assert marker in text  # sensor1's tolerances end there
    table = "[sensor.silicone]\n" + (
        "" if series == DEFAULT_RELAXATION else f"relaxation = {[list(p) for p in series]}\n"
    )
    return text.replace(marker, f"seed = {seed}\n" + (table if memory else ""), 1)


def scene_path(memory: bool, tmp: Path, seed: int = 1, series: Series = DEFAULT_RELAXATION) -> Path:
    path = tmp / f"scene-{'memory' if memory else 'spring'}-{seed}.toml"
    path.write_text(scene_text(memory, seed, series))
    return path


def scene(memory: bool, tmp: Path, seed: int = 1, series: Series = DEFAULT_RELAXATION) -> PhysicalScene:
    s = load_scene(scene_path(memory, tmp, seed, series))
    assert isinstance(s, PhysicalScene)
    return s


class Sine:
    """``amplitude`` (6,) N, Nm times sin(2 pi f (t - start)) from ``start_s`` on."""

    def __init__(self, amplitude: np.ndarray, f_hz: float, start_s: float):
        self.amplitude, self.f_hz, self.start_s = amplitude, f_hz, start_s

    def wrench(self, t: float) -> np.ndarray:
        return (
            self.amplitude * math.sin(2 * math.pi * self.f_hz * (t - self.start_s))
            if t >= self.start_s
            else np.zeros(6)
        )


class Training:
    """A tool pressed and dragged: each force axis a sum of sinusoids at 0.3-3 Hz, random
    phases (seeded), 0.5-3 N in all, after a rest of ``start_s``."""

    def __init__(self, start_s: float, seed: int = 7):
        rng = np.random.default_rng(seed)
        self.f = rng.uniform(0.3, 3.0, (3, 4))
        self.a = rng.uniform(0.2, 0.6, (3, 4))
        self.phase = rng.uniform(0, 2 * np.pi, (3, 4))
        self.start_s = start_s

    def wrench(self, t: float) -> np.ndarray:
        if t < self.start_s:
            return np.zeros(6)
        s = t - self.start_s
        ramp = min(1.0, s)  # pressed in over a second
        f = ramp * (
            np.sum(self.a * np.sin(2 * np.pi * self.f * s + self.phase), axis=1) + np.array([0.5, 0, 1.0])
        )
        return np.concatenate([f, np.zeros(3)])


@dataclass
class Setting:
    name: str
    osr: int
    dig_filt: int
    rate_hz: float
    averaging: int = 1
    estimator: str = "linear"
    scheduler: str | None = None  # None: the configuration's


def run(
    config: Config,
    cal: Calibration,
    sc: PhysicalScene,
    load,
    seconds: float,
    setting: Setting,
    compensate: bool,
    flags: list | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """sensor1's published wrench under ``load``: (times from the scene's start (s), wrench (n, 6),
    truth (n, 6)), the daemon in process on a virtual clock cycling at ``setting``'s rate; each
    sample's flags appended to ``flags`` when given."""
    sc.set_load(0, load)
    bus = simulated_bus(sc, clock=VirtualClock(), bus_hz=config.bus_hz, seed=11)
    settings = replace(config.settings, osr=setting.osr, dig_filt=setting.dig_filt)
    sensors = [
        replace(s, calibration=cal, estimator=setting.estimator) if i == 0 else s
        for i, s in enumerate(config.sensors)
    ]
    cfg = replace(
        config,
        settings=settings,
        averaging=setting.averaging,
        rate_hz=setting.rate_hz,
        temperature_every=0,
        readback_every=0,
        tool_poses={},
        sensors=sensors,
        scheduler=setting.scheduler or config.scheduler,
        stuck_cycles=stuck_cycles_for(settings),
    )
    out = Capture()
    daemon = Daemon(cfg, bus, out, None, clock=bus.monotonic)  # type: ignore[arg-type]
    daemon.start()
    if not compensate:
        daemon.sensors[0].creep = CreepCompensation(None, setting.rate_hz)  # the daemon as without it
    period = 1.0 / setting.rate_hz
    t, w, truth = [], [], []
    deadline = bus.monotonic()
    while bus.monotonic() - bus.epoch < seconds:
        bus.sleep(max(0.0, deadline - bus.monotonic()))
        deadline += period
        daemon.cycle()
        s = out.last["wrench/sensor1"]
        now = s.t_mono - bus.epoch
        t.append(now)
        w.append(s.values if not s.flags & wire.FLAG_INVALID else np.full(6, np.nan))
        if flags is not None:
            flags.append(s.flags)
        truth.append(load.wrench(now))
    bus.close()
    return np.array(t), np.array(w), np.array(truth)


#: The step's error is judged on means over this long (s): a single sample's noise is 0.03-0.06 N
#: on Fx at the loop settings here, 1.5-3 % of the step, so the aim of 2 % is a figure of the
#: estimate, not of one reading; 0.25 s divides the noise by 5 and is shorter than any creep.
STEP_WINDOW_S = 0.25


def step_figures(t, w, truth, at_s: float) -> tuple[float, float, float, float, float]:
    """On Fx, from 0.5 s after the step on, the wrench at rest in the second before it taken as
    zero (a tare): the largest |error| of `STEP_WINDOW_S` means and of single samples (% of the
    step); the time to half the step (ms); and the error's two parts (% of the step): the
    estimator's static error (its reading over the hold's last second against the truth,
    signed) and the creep it leaves (the largest |mean| against that last second's reading)."""
    after = t >= at_s + 0.5
    rest = float(np.nanmean(w[(t > at_s - 1.0) & (t < at_s), 0]))
    error = w[after, 0] - rest - truth[after, 0]
    windows = np.floor((t[after] - at_s - 0.5) / STEP_WINDOW_S)
    means = np.array([np.nanmean(error[windows == k]) for k in np.unique(windows)])
    half = t[(t >= at_s) & (w[:, 0] - rest >= STEP_N / 2)]
    last = float(np.nanmean(error[t[after] > t[-1] - 1.0]))
    return (
        float(np.max(np.abs(means))) / STEP_N * 100,
        float(np.nanmax(np.abs(error))) / STEP_N * 100,
        (float(half[0]) - at_s) * 1e3 if len(half) else float("nan"),
        last / STEP_N * 100,
        float(np.max(np.abs(means - last))) / STEP_N * 100,
    )


def sine_figures(t, w, f_hz: float, start_s: float) -> tuple[float, float]:
    """(amplitude / 2 N, lag in ms) of Fx over whole periods from a second after the start."""
    periods = math.floor((t[-1] - start_s - 1.0) * f_hz)
    sel = (t >= start_s + 1.0) & (t < start_s + 1.0 + periods / f_hz) & np.isfinite(w[:, 0])
    x = 2 * np.pi * f_hz * (t[sel] - start_s)
    X = np.column_stack([np.sin(x), np.cos(x), np.ones(len(x))])
    (a, b, _), *_ = np.linalg.lstsq(X, w[sel, 0], rcond=None)
    return float(np.hypot(a, b)) / STEP_N, float(-np.arctan2(b, a)) / (2 * np.pi * f_hz) * 1e3


def validation(
    config: Config, cal: Calibration, sc: PhysicalScene, dataset, setting: Setting, compensate: bool
) -> np.ndarray:
    """RMSE (6,) of each 100 g validation pose's mean published wrench (the pose held 1 s, the
    robot's dwell), the daemon running through the poses in the dataset's order."""
    poses = [
        (dataset.wrench[k], dataset.rotation[k])
        for k in range(len(dataset))
        if dataset.split[k] == "validation"
    ]

    class Robot:  # the load and the orientation at once, as CalibrationRobotLoad
        def wrench(self, t: float) -> np.ndarray:
            return poses[min(int(t), len(poses) - 1)][0] if t >= 0 else np.zeros(6)

    t, w, truth = run(config, cal, sc, Robot(), float(len(poses)), setting, compensate)
    errors = [np.nanmean(w[(t >= k) & (t < k + 1)], axis=0) - poses[k][0] for k in range(len(poses))]
    return np.sqrt(np.nanmean(np.square(errors), axis=0))


def cost(quick: bool, series: Series) -> dict[str, float]:
    """The stage's time a sample (us, 6 axes), and the scene's a simulated second of a moving
    load with and without the memory (ms)."""
    inverse = CreepInverse(Relaxation.from_pairs(series), 0.01)
    y = np.ones(6)
    n = 2000 if quick else 20000
    t0 = time.perf_counter()
    for _ in range(n):
        inverse.apply(y)
    stage_us = (time.perf_counter() - t0) / n * 1e6
    out = {"stage_us": stage_us}
    for memory in (False, True):
        with tempfile.TemporaryDirectory() as tmp:
            sc = scene(memory, Path(tmp), series=series)
        sc.set_load(0, Sine(np.array([2.0, 0, 0, 0, 0, 0]), 1.0, 0.0))
        t0 = time.perf_counter()
        for k in range(1000):  # one second at 1 ms, the 8 chips of sensor1 read each step
            for a in sc.sensors[0].addresses:
                sc.field_t(a, k * 1e-3)
        out["scene_ms_memory" if memory else "scene_ms_spring"] = (time.perf_counter() - t0) * 1e3
    return out


#: Quick (CI): the documented commands with fewer poses and readings and a shorter hold, the
#: nonlinear fit skipped; the full run takes every default.
QUICK_ARGS = [
    "--poses",
    "40",
    "--validation-poses",
    "12",
    "--samples",
    "20",
    "--check-poses",
    "3",
    "--hold-s",
    "20",
]


def calibrated_part(
    quick: bool, tmp: Path, seed: int, series: Series = DEFAULT_RELAXATION
) -> tuple[list[str], Dataset, Calibration]:
    """Part ``seed`` with ``series``, calibrated as a user does it: `ftsensord dataset
    --scene S --sensor sensor1 -o ds.json` then `ftsensord calibrate ds.json -o cal.json` (at
    their defaults; quick: `QUICK_ARGS`, --linear-only): the two commands, the dataset and the
    calibration they wrote."""
    ds, cal = tmp / f"ds-{seed}.json", tmp / f"cal-{seed}.json"
    dataset_args = [
        "dataset",
        "--scene",
        str(scene_path(True, tmp, seed, series)),
        "--sensor",
        "sensor1",
        "-o",
        str(ds),
    ]
    calibrate_args = ["calibrate", str(ds), "-o", str(cal)]
    if quick:
        dataset_args += QUICK_ARGS
        calibrate_args += ["--linear-only"]
    with contextlib.redirect_stderr(io.StringIO()):  # the nonlinear fit's progress lines
        if cli.main(dataset_args) != 0 or cli.main(calibrate_args) != 0:
            raise SystemExit(f"part {seed}: the documented commands failed (above)")
    shown = [" ".join(["ftsensord", *a]).replace(str(tmp) + "/", "") for a in (dataset_args, calibrate_args)]
    return shown, Dataset.load(ds), Calibration.load(cal)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small and short; written only to --out")
    parser.add_argument(
        "--out",
        type=Path,
        help="folder for silicone-figures.md and silicone.png "
        "(default: docs/results/; --quick: none, nothing written)",
    )
    args = parser.parse_args()
    quick = args.quick
    series = HARSH if quick else DEFAULT_RELAXATION
    config = load_config(builtin_path("sim.toml"))
    parts = PARTS[:1] if quick else PARTS
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        calibrated = {seed: calibrated_part(quick, tmp, seed, series) for seed in parts}
        lines = report_header(quick, calibrated, series)
        default = Setting("default (burst, 100 Hz)", config.settings.osr, config.settings.dig_filt, 100.0)
        settings = [default]
        if not quick:
            settings += [
                Setting("faster (OSR 0, DIG_FILT 2, 140 Hz)", 0, 2, 140.0),
                Setting("default, averaging 4", config.settings.osr, config.settings.dig_filt, 100.0, 4),
                Setting(
                    "default, nonlinear estimator",
                    config.settings.osr,
                    config.settings.dig_filt,
                    100.0,
                    1,
                    "nonlinear",
                ),
            ]
        # Each part compensated at the default loop; the first also without the compensation and at
        # the other loops; and the default scene's own part (seed 1) as a perfect spring with the
        # packaged calibration fitted on it: what a part does without its memory.
        cases = [(parts[0], st, True, comp) for st in settings for comp in (True, False)]
        cases += [(seed, default, True, True) for seed in parts[1:]] + [(1, default, False, False)]
        rows = []
        traces: dict = {}
        hold = 8.0 if quick else 32.0
        spring = Calibration.load(
            builtin_path("sim-sensor1.json")
        )  # the packaged one: fitted on seed 1, a spring
        for seed, st, memory, comp in cases:
            label = (
                "memory, compensated" if comp else ("memory, not compensated" if memory else "perfect spring")
            )
            part = calibrated[seed][2] if memory else spring
            dataset = calibrated[seed if memory else parts[0]][1]
            first = seed == parts[0] and st is default
            t, w, truth = run(
                config,
                part,
                scene(memory, tmp, seed, series),
                StepLoad(2.0, np.zeros(6), np.array([STEP_N, 0, 0, 0, 0, 0])),
                hold,
                st,
                comp,
            )
            step_err, step_single, half_ms, static, creep_left = step_figures(t, w, truth, 2.0)
            if first or not memory:
                traces[("step", label)] = (t, w[:, 0], truth[:, 0])
            sines = []
            for f in FREQUENCIES_HZ[:2] if quick else FREQUENCIES_HZ:
                t, w, truth = run(
                    config,
                    part,
                    scene(memory, tmp, seed, series),
                    Sine(np.array([STEP_N, 0, 0, 0, 0, 0]), f, 1.0),
                    1.0 + max(3.0, 4 / f) if quick else 1.0 + max(6.0, 10 / f),
                    st,
                    comp,
                )
                sines.append(sine_figures(t, w, f, 1.0))
                if (first or not memory) and f == 2.0:
                    traces[("sine", label)] = (t, w[:, 0], truth[:, 0])
            t, w, truth = run(
                config,
                part,
                scene(memory, tmp, seed, series),
                Training(1.0),
                6.0 if quick else 21.0,
                st,
                comp,
            )
            sel = t >= 2.0
            training = float(np.sqrt(np.nanmean(np.square(w[sel, :3] - truth[sel, :3]))))
            # The validation poses: the part's own dataset's (the spring's: the first part's poses).
            val = validation(config, part, scene(memory, tmp, seed, series), dataset, st, comp)
            rows.append(
                (
                    seed,
                    st.name,
                    label,
                    step_err,
                    step_single,
                    half_ms,
                    static,
                    creep_left,
                    sines,
                    training,
                    val,
                )
            )
        lines += report_rows(rows, quick)
    c = cost(quick, series)
    lines += [
        "",
        "## Cost",
        "",
        f"The stage: {c['stage_us']:.1f} us a sample (6 axes, 2 terms; `CreepInverse.apply` alone, "
        f"{2000 if quick else 20000} samples). The scene: a simulated second of a moving load, sensor1's "
        f"8 chips read every 1 ms step: {c['scene_ms_spring']:.0f} ms with a perfect spring, "
        f"{c['scene_ms_memory']:.0f} ms with the memory; a static scene keeps no memory at all "
        "(`SimSensor.memory` is None).",
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out is not None or not quick:
        out = args.out or DOCS
        (out / "silicone-figures.md").write_text(text)
        plot(traces, out / "silicone.png")
    return 0


def plot(traces: dict, path: Path) -> None:
    """The held step and the 2 Hz sine at the default loop: published Fx against the truth."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib is missing (pip install 'ftsensord[plot]'): no plot", file=sys.stderr)
        return
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for ax, kind, span in ((axes[0], "step", (1.0, 32.0)), (axes[1], "sine", (4.0, 5.5))):
        truth_drawn = False
        for (k, label), (t, w, truth) in traces.items():
            if k != kind:
                continue
            sel = (t >= span[0]) & (t <= span[1])
            if not truth_drawn:
                ax.plot(t[sel], truth[sel], "k", lw=2, label="applied (the scene's truth)")
                truth_drawn = True
            ax.plot(t[sel], w[sel], lw=1, label=label)
        ax.set_xlabel("time (s)")
        ax.set_ylabel("Fx (N)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    axes[0].set_title("2 N held 30 s (default loop, 100 Hz)")
    axes[1].set_title("2 N at 2 Hz")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def report_header(quick: bool, calibrated: dict, series: Series) -> list[str]:
    seed, (commands, dataset, cal) = next(iter(calibrated.items()))
    dwell = float(np.median(dataset.times_s[:, 2] - dataset.times_s[:, 0]))
    sizes = (
        "the commands' defaults: 193 fit, 60 validation, 24 no-load (first, before any load) and 24 check "
        "poses of 100 readings, the step-and-hold 60 s a pose read every 10 ms, the nonlinear fit"
        if not quick
        else "quick: " + " ".join(QUICK_ARGS) + ", --linear-only"
    )
    lines = [
        "# The silicone's memory: figures",
        "",
        f"Made by `python -m benchmarks.accuracy.creep`{' --quick' if quick else ''}. "
        "The parts: the default scene (the "
        f"Earth's field, 48 uT: a room) with sensor1 the as-built part of seed {', '.join(map(str, calibrated))} "
        + (
            f"and `[sensor.silicone]` (the default series {list(map(list, series))}), each calibrated "
            if series == DEFAULT_RELAXATION
            else f"and `[sensor.silicone]` with the series {list(map(list, series))} (quick: not the default, "
            "a silicone whose creep a short run shows), each calibrated "
        )
        + f"by the two documented commands ({sizes}; a pose's dwell {dwell:.2f} s; the static fits made on the "
        "loads the silicone carried over each dwell, docs/guide/calibration.md). For the part of seed "
        f"{seed}:",
        "",
        "```",
        *commands,
        "```",
        "",
        "(the scene file is the default scene with its `seed = 1` line of sensor1 replaced by "
        "`seed = N` and `[sensor.silicone]`). The daemon then runs each calibration file as written; the "
        "linear estimator, and the nonlinear one where a row says so.",
        "",
        "## Identification",
        "",
        "| part | term | fraction (scene) | fraction (identified) | error | time (scene, s) | time (identified, s) "
        "| error | scale |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for seed, (_, _, cal) in calibrated.items():
        found = cal.silicone
        if found is None:
            lines.append(f"| {seed} | not identified: {cal.report['silicone']} | | | | | | | |")
            continue
        got = found.relaxation
        truth = Relaxation.from_pairs(series)
        for k, (g0, t0) in enumerate(zip(truth.fractions, truth.times_s)):
            g1, t1 = (
                (got.fractions[k], got.times_s[k]) if k < len(got.fractions) else (float("nan"), float("nan"))
            )
            lines.append(
                f"| {seed} | {k + 1} | {g0:.3f} | {g1:.4f} | {100 * (g1 / g0 - 1):+.1f} % | {t0:g} | "
                f"{t1:.3f} | {100 * (t1 / t0 - 1):+.1f} % | {found.scale:.4f} |"
            )
    lines += [
        "",
        "Scale: how the static K reads a long-held load, per unit (1 when it is the long-term stiffness).",
        "",
        "Validation RMSE of the static fit (the datasets' pose means):",
        "",
    ]
    for seed, (_, _, cal) in calibrated.items():
        lines.append(
            f"- part {seed}: "
            + ", ".join(f"{k} {v:.4f}" for k, v in cal.report["validation_rmse"].items())
            + (
                "; nonlinear: "
                + ", ".join(f"{k} {v:.4f}" for k, v in cal.report["nonlinear"]["validation_rmse"].items())
                if cal.report.get("nonlinear")
                else ""
            )
        )
    return lines


def report_rows(rows: list, quick: bool) -> list[str]:
    freqs = FREQUENCIES_HZ[:2] if quick else FREQUENCIES_HZ
    out = [
        "",
        "## Moving loads",
        "",
        "Step: 2 N on Fx at 2 s, held 30 s, tared at rest before it; the largest |error| from 0.5 s "
        f"after it on (% of the step; the aim: 2 %) of {STEP_WINDOW_S:g} s means and of single samples "
        "(their noise alone is 1.5-3 % of the step), and the time to half the step; the means' error in two "
        "parts: the estimator's static error (its reading over the hold's last second against the truth; a "
        "part without a memory has it too) and the creep left (the largest |mean| against that reading). "
        "Sines: 2 N on Fx; amplitude "
        "(published / applied; the aim: within 3 %) and lag (ms), each fitted over whole periods. Training: RMSE "
        "over the force axes (N). Validation: the 100 g poses' means through the daemon (each held 1 s), RMSE per "
        "axis (N, mNm); Table II is 0.234, 0.114, 0.378 N, 4.1, 10.6, 8.5 mNm. The perfect spring: the default "
        "scene's own part (seed 1) without the memory, with the packaged calibration fitted on it, on the first "
        "part's validation poses.",
        "",
        "| part | loop | silicone | step error, means (%) | single samples (%) | step to half (ms) | "
        "static error (%) | creep left (%) | "
        + " | ".join(f"{f:g} Hz amplitude / lag (ms)" for f in freqs)
        + " | training RMSE (N) | 100 g validation RMSE (N x3, mNm x3) | within Table II |",
        "|---|---|---|---|---|---|---|---|" + "---|" * len(freqs) + "---|---|---|",
    ]
    for seed, name, label, err, single, half, static, creep_left, sines, training, val in rows:
        val_text = ", ".join([f"{v:.3f}" for v in val[:3]] + [f"{v * 1e3:.2f}" for v in val[3:]])
        out.append(
            f"| {seed} | {name} | {label} | {err:.2f} | {single:.2f} | {half:.0f} | {static:+.2f} | {creep_left:.2f} | "
            + " | ".join(f"{a:.4f} / {lag:.1f}" for a, lag in sines)
            + f" | {training:.4f} | {val_text} | {'yes' if np.all(val <= TABLE_II) else 'no'} |"
        )
    return out


if __name__ == "__main__":
    sys.exit(main())
