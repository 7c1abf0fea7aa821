"""Coverage of each sample's sigma: the fraction of samples whose error against the scene's
truth lies within 1 and 2 sigma, per axis, at rest and under held loads, per estimator,
smoothing and chips; written as docs/results/coverage.md.

For each part (the default scene's room, sensor1 built with tolerance seed ``--parts``, seeds
no test uses), the documented commands calibrate it at their defaults (the nonlinear fit
included): ``ftsensord dataset --scene S --seed N`` and ``ftsensord calibrate``. Then, for each
case (`CASES`), a daemon on that scene (in process, virtual clock, the packaged chip
settings) tares at rest (100 samples, the default) and publishes ``--rest-samples`` samples at
rest, then ``--samples`` samples at each of ``--loads`` held loads drawn uniformly within the
calibration's range (its file's ``wrench_range``, every axis at once), each after the filter
and the load have settled. A sample's error is its wrench minus the truth (the held load: the
tare was at no load). Run:

    python -m benchmarks.accuracy.coverage [--parts 71 72 73] [--loads 60] [--samples 20]
    python -m benchmarks.accuracy.coverage --quick --out /tmp/coverage.md   # the page's structure
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import io
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from benchmarks.common import RESULTS, machine
from ftsensord import cli
from ftsensord.calibration.calfile import Calibration
from ftsensord.config.file import load_config
from ftsensord.protocol import wire
from ftsensord.sim import load_scene
from ftsensord.sim.loads import StaticLoad
from ftsensord.sim.scene import default_scene_path
from ftsensord.testing.harness import InProcess

AXES = ("Fx", "Fy", "Fz", "Mx", "My", "Mz")
#: The issue's targets: within 1 sigma 68 % +- 6, within 2 sigma 95 % +- 3.
TARGETS = {1: (62.0, 74.0), 2: (92.0, 98.0)}
#: The chip left out in the "one chip out" cases (sensor1's fourth).
CHIP_OUT = 0x0F
#: Quick runs: the dataset's sizes (a few minutes less of calibration), the fit kept whatever it
#: gives (``--allow-poor-fit``): the page's structure, not its figures.
QUICK_DATASET = [
    "--poses",
    "60",
    "--validation-poses",
    "15",
    "--samples",
    "20",
    "--check-poses",
    "3",
    "--hold-s",
    "0",
]


@dataclass(frozen=True)
class Case:
    name: str
    estimator: str
    averaging: int = 1
    lowpass_hz: float = 0.0
    chip_out: bool = False


CASES = (
    Case("linear", "linear"),
    Case("nonlinear", "nonlinear"),
    Case("linear, averaging 10 + low-pass 5 Hz", "linear", 10, 5.0),
    Case("nonlinear, averaging 10 + low-pass 5 Hz", "nonlinear", 10, 5.0),
    Case(f"linear, chip 0x{CHIP_OUT:02X} out", "linear", chip_out=True),
    Case(f"nonlinear, chip 0x{CHIP_OUT:02X} out", "nonlinear", chip_out=True),
)


def scene_text(seed: int) -> str:
    """The default scene with sensor1 made with tolerance seed ``seed``."""
    return default_scene_path().read_text().replace("seed = 1 ", f"seed = {seed} ", 1)


def calibrate(folder: Path, seed: int, quick: bool) -> tuple[list[str], Path]:
    """Part ``seed`` calibrated by the documented commands: the commands as a user types them,
    and the calibration file."""
    (folder / "scene.toml").write_text(scene_text(seed))
    dataset = [
        "dataset",
        "-o",
        str(folder / "ds.json"),
        "--scene",
        str(folder / "scene.toml"),
        "--seed",
        str(seed),
    ]
    calibrate = ["calibrate", str(folder / "ds.json"), "-o", str(folder / "cal.json")]
    if quick:
        dataset += QUICK_DATASET
        calibrate += ["--allow-poor-fit"]
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        if cli.main(dataset) != 0 or cli.main(calibrate) != 0:
            raise SystemExit(f"part {seed}: the documented commands failed")
    shown = [" ".join(["ftsensord", *a]).replace(str(folder) + "/", "") for a in (dataset, calibrate)]
    return shown, folder / "cal.json"


def config_text(cal: Path, case: Case) -> str:
    return f"""
version = 1
bus = "sim:scene.toml"
rate_hz = 100
scheduler = "overlapped"
temperature_every = 0
averaging = {case.averaging}
lowpass_hz = {case.lowpass_hz}
[[sensor]]
name = "sensor1"
addresses = [0x0C, 0x0D, 0x0E, 0x0F, 0x10, 0x11, 0x12, 0x13]
calibration = "{cal}"
estimator = "{case.estimator}"
"""


def run_case(
    folder: Path, cal: Path, seed: int, case: Case, loads: np.ndarray, samples: int, rest_samples: int
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The errors and sigmas (samples x 6 each) at rest and under the held ``loads`` of part
    ``seed`` in ``case``."""
    (folder / "ftsensord.toml").write_text(config_text(cal, case))
    rig = InProcess(
        load_config(folder / "ftsensord.toml"), load_scene(folder / "scene.toml"), subscribe=b"", seed=seed
    )
    try:
        p = rig.daemon.sensors[0]
        # The filter's memory (to 1e-4 of an input) and 20 cycles more: the load and the silicone settle.
        settle = p.filter.reach + 20
        for _ in range(120):
            step(rig)
        flux = []
        for _ in range(100):
            step(rig)
            flux.append(p.last_flux.copy())
        p.tare(np.mean(flux, axis=0), None, len(flux))
        if case.chip_out:
            rig.bus.detach(CHIP_OUT)
        out: dict[str, tuple[list[np.ndarray], list[np.ndarray]]] = {"rest": ([], []), "held": ([], [])}
        for k, load in enumerate([np.zeros(6), *loads]):
            rig.scene.set_load(0, StaticLoad(np.asarray(load, dtype=float)))
            for _ in range(settle):
                step(rig)
            which = "rest" if k == 0 else "held"
            for _ in range(rest_samples if k == 0 else samples):
                w, s = step(rig)
                out[which][0].append(w - load)
                out[which][1].append(s)
    finally:
        rig.close()
    return {name: (np.array(e), np.array(s)) for name, (e, s) in out.items()}


def step(rig: InProcess) -> tuple[np.ndarray, np.ndarray]:
    """One cycle; sensor1's wrench and sigma as published (NaN when not published)."""
    deadline = rig.clock.now() + rig.daemon.period_s
    rig.daemon.cycle()
    rig.clock.wait_until(deadline)
    w = s = np.full(6, np.nan)
    while rig.sub.poll(0):
        x = wire.decode(rig.sub.recv())
        if x.topic == "wrench/sensor1":
            w = x.values
        elif x.topic == "sigma/wrench/sensor1":
            s = x.values
    return w, s


def coverage(errors: np.ndarray, sigmas: np.ndarray) -> tuple[int, int, dict[int, np.ndarray], np.ndarray]:
    """Samples with a sigma, samples without, the % within 1 and 2 sigma per axis, the median sigma."""
    ok = np.all(np.isfinite(sigmas), axis=1) & np.all(np.isfinite(errors), axis=1)
    e, s = errors[ok], sigmas[ok]
    within = {k: np.mean(np.abs(e) <= k * s, axis=0) * 100 for k in (1, 2)}
    return int(ok.sum()), int((~ok).sum()), within, np.median(s, axis=0)


def cell(value: float, k: int) -> str:
    low, high = TARGETS[k]
    return f"{value:.0f} %" + ("" if low <= value <= high else " (x)")


def page(results: dict, commands: list[str], args: argparse.Namespace, elapsed_s: float, ranges: dict) -> str:
    lines = [
        "# Each sample's sigma: coverage",
        "",
        f"Made by `python -m benchmarks.accuracy.coverage{' --quick' if args.quick else ''}"
        f" --parts {' '.join(map(str, args.parts))} --loads {args.loads} --samples {args.samples} "
        f"--rest-samples {args.rest_samples}` on {datetime.datetime.now(datetime.UTC):%Y-%m-%d %H:%M} UTC, "
        f"{machine()}, in {elapsed_s / 60:.0f} min."
        + (
            " **Quick run: small datasets, few samples; the page's structure, not its figures.**"
            if args.quick
            else ""
        ),
        "",
        "What it measures: the fraction of published samples whose error against the scene's truth lies "
        "within 1 and 2 of the sigma published with them (`sigma/wrench/sensor1`), per axis. The aim: "
        "68 % +- 6 within 1 sigma and 95 % +- 3 within 2; a figure outside it is marked (x).",
        "",
        f"The parts: the default scene (the Earth's field, 48 uT: a room) with sensor1 the as-built part of "
        f"tolerance seed {', '.join(map(str, args.parts))}, each calibrated by the documented commands at their "
        f"defaults{' (quick: smaller)' if args.quick else ''}; for the part of seed {args.parts[0]}:",
        "",
        "```",
        *commands,
        "```",
        "",
        "(the scene file is the default scene with sensor1's `seed = 1` replaced). Then per case a daemon on "
        "that scene (in process, virtual clock, 100 Hz, the packaged chip settings, no temperature stage) "
        "tares at rest (100 samples), publishes "
        f"{args.rest_samples} samples at rest, then {args.samples} samples at each of {args.loads} held loads a "
        "part, drawn uniformly within the calibration's range on every axis at once (the file's "
        "`wrench_range`), each after the filter's memory and 20 cycles more. A chip out: detached from the bus "
        "after the tare (the daemon estimates from the 7 left, flagged `degraded`). The calibration ranges "
        "(N, Nm): "
        + "; ".join(f"part {seed}: " + ", ".join(f"{v:.3g}" for v in r) for seed, r in ranges.items())
        + ".",
        "",
        "| case | load | samples | within | " + " | ".join(AXES) + " | median sigma (N, Nm) |",
        "|---|---|---|---|" + "---|" * 6 + "---|",
    ]
    unknown_total = 0
    for case in CASES:
        for which in ("rest", "held"):
            parts = results[case.name][which]
            n, unknown, within, median = coverage(
                np.concatenate([e for e, _ in parts]), np.concatenate([s for _, s in parts])
            )
            unknown_total += unknown
            for k in (1, 2):
                lines.append(
                    f"| {case.name} | {which} | {n} | {k} sigma | "
                    + " | ".join(cell(v, k) for v in within[k])
                    + " | "
                    + (", ".join(f"{v:.3g}" for v in median) if k == 1 else "")
                    + " |"
                )
    lines += [
        "",
        f"Samples without a sigma (NaN: none published, or a nonlinear estimate that fell back) are left out: "
        f"{unknown_total} in all. With the filter on, neighbouring samples are correlated: the held loads' "
        "figures rest on the loads' count more than on the samples'.",
        "",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", type=int, nargs="+", default=[71, 72, 73])
    parser.add_argument("--loads", type=int, default=60, help="held loads a part (default 60)")
    parser.add_argument("--samples", type=int, default=20, help="samples a held load (default 20)")
    parser.add_argument("--rest-samples", type=int, default=300, help="samples at rest a part (default 300)")
    parser.add_argument(
        "--quick", action="store_true", help="one small part, few samples: the page's structure"
    )
    parser.add_argument("--out", type=Path, help="the page to write (default docs/results/coverage.md)")
    args = parser.parse_args(argv)
    if args.quick:
        args.parts, args.loads, args.samples, args.rest_samples = args.parts[:1], 4, 5, 20
    out = args.out or RESULTS / "coverage.md"
    began = time.monotonic()
    results: dict[str, dict[str, list]] = {c.name: {"rest": [], "held": []} for c in CASES}
    commands: list[str] = []
    ranges: dict[int, np.ndarray] = {}
    for seed in args.parts:
        with tempfile.TemporaryDirectory() as tmp:
            folder = Path(tmp)
            shown, cal = calibrate(folder, seed, args.quick)
            commands = commands or shown
            ranges[seed] = np.asarray(Calibration.load(cal).wrench_range)
            rng = np.random.default_rng(seed * 100)
            loads = rng.uniform(-1.0, 1.0, (args.loads, 6)) * ranges[seed]
            for case in CASES:
                for which, got in run_case(
                    folder, cal, seed, case, loads, args.samples, args.rest_samples
                ).items():
                    results[case.name][which].append(got)
            print(f"part {seed} done, {time.monotonic() - began:.0f} s", flush=True)
    out.write_text(page(results, commands, args, time.monotonic() - began, ranges))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
