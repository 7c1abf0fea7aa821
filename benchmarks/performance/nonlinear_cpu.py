"""The nonlinear estimator's CPU a sample while the load moves, readings replayed in a tight loop.

sensor1 of the default scene (the room and the as-built part the packaged calibrations
were fitted on) under a load moving at ``--hz`` (default 1.3 Hz) on every axis at once,
each at ``--fraction`` (default 40 %) of the sensor's range (50, 50, 20 N, 0.2 Nm), the
axes a sixth of a period apart, sampled at 100 Hz for a whole number of periods (so the
replay loops without a jump). Each reading is the scene's flux at that instant with the
emulated chip's noise, quantised to the chip's LSB as the chip does. The packaged
calibration's nonlinear estimator (`model.nonlinear.NonlinearEstimator`, the daemon's)
estimates every reading in turn, warm-started as in the daemon, ``--loops`` times round
the readings; each call's CPU time (``time.process_time``: a preemption on a busy host
does not count) gives mean, p50, p99 and max. Both solvers (`nlcompiled`): numpy's and the
compiled one (the installed library, else built from the source for the run where a C
compiler is), in interleaved rounds. The same readings at rest (the load's mean,
zero) give the figure the at-rest benchmark (`cycle_cpu.py`) reports, for comparison.
Accuracy: each estimate's wrench K (xi - xi0) against the scene's load (RMS per axis),
and how many did not converge (the daemon falls back to the linear estimate for those).

    python -m benchmarks.performance.nonlinear_cpu                  # the docs' figures (about 20 s)
    python -m benchmarks.performance.nonlinear_cpu --quick --json   # CI: a few hundred samples
"""

from __future__ import annotations

import argparse
import json
import math
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import machine, pin_to_core
from ftsensord.config.file import builtin_path, load_config
from ftsensord.model import nlcompiled
from ftsensord.model.linear import SENSOR_RANGE
from ftsensord.model.nonlinear import NonlinearEstimator
from ftsensord.sim import NoiseModel, default_scene

RATE_HZ = 100.0  # the daemon's default rate: a reading every 10 ms


class MovingLoad:
    """Every axis at ``fraction`` of the sensor's range, at ``hz``, a sixth of a period apart (N, Nm)."""

    def __init__(self, fraction: float, hz: float):
        self.amplitude, self.omega = fraction * SENSOR_RANGE, 2 * math.pi * hz
        self.phase = np.arange(6) * (2 * math.pi / 6)

    def wrench(self, t: float) -> np.ndarray:
        return self.amplitude * np.sin(self.omega * t + self.phase)


def readings(fraction: float, hz: float, periods: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """sensor1's flux (samples x 24, T) under the moving load, and the load (samples x 6)."""
    config = load_config(builtin_path("sim.toml"))
    settings, addresses = config.settings, config.sensors[0].addresses
    scene = default_scene()
    load = MovingLoad(fraction, hz)
    scene.set_load(0, load)
    noise, rng = NoiseModel(), np.random.default_rng(seed)
    lsb = np.array([settings.sensitivity_ut(a) for a in "xyz"])
    sigma = np.array([noise.sigma_ut(a, settings.tconvm_us()) for a in "xyz"])
    n = max(1, round(periods * RATE_HZ / hz))
    flux, truth = np.empty((n, 3 * len(addresses))), np.empty((n, 6))
    for k in range(n):
        t = k / RATE_HZ
        ut = np.array([scene.field_t(a, t) * 1e6 for a in addresses])
        flux[k] = (np.round((ut + rng.normal(0.0, 1.0, ut.shape) * sigma) / lsb) * lsb).ravel() * 1e-6
        truth[k] = load.wrench(t)
    return flux, truth


def replay(
    estimator: NonlinearEstimator, flux: np.ndarray, loops: int
) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Each reading estimated in turn, ``loops`` times round: CPU a call (s), the last
    loop's wrenches (NaN where not converged), calls not converged, iterations in all."""
    cpu = np.empty(loops * len(flux))
    wrench = np.full((len(flux), 6), np.nan)
    failed = iterations = 0
    clock, estimate = time.process_time, estimator.estimate
    for j in range(loops):
        for k, b in enumerate(flux):
            t0 = clock()
            e = estimate(b)
            cpu[j * len(flux) + k] = clock() - t0
            iterations += e.iterations
            if not e.converged:
                failed += 1
            elif j == loops - 1:
                wrench[k] = estimator.stiffness @ (e.xi - estimator.zero_twist)
    return cpu, wrench, failed, iterations


def stats_us(cpu: np.ndarray) -> dict[str, float]:
    us = cpu * 1e6
    return {
        "mean": float(us.mean()),
        "p50": float(np.percentile(us, 50)),
        "p99": float(np.percentile(us, 99)),
        "max": float(us.max()),
    }


def compiled_library(folder: str) -> tuple[Path | None, str]:
    """The compiled solve's library: the installed one (beside `nlcompiled`), else built
    into ``folder`` from the source when a C compiler is here; and where it came from."""
    installed = nlcompiled.library_path()
    if installed is not None:
        return installed, "installed"
    if nlcompiled.compiler() is None:
        return None, "none (no C compiler)"
    return nlcompiled.compile_library(Path(folder)), "compiled from the source for this run"


def measure(fraction: float, hz: float, periods: int, loops: int) -> dict[str, Any]:
    """Both solvers (numpy's and the compiled one, where it builds) on the same readings,
    in interleaved rounds (one replay each a round, which goes first alternating), so a
    change of the host's load hits both. The top level is the compiled one's when there is
    one (what `solver = "auto"` runs where it is installed), else numpy's."""
    config = load_config(builtin_path("sim.toml"))
    nl = config.sensors[0].calibration.nonlinear
    assert nl is not None  # the packaged calibrations have one
    flux, truth = readings(fraction, hz, periods)
    rest, _ = readings(0.0, hz, periods, seed=1)
    out: dict[str, Any] = {
        "samples": len(flux),
        "loops": loops,
        "fraction": fraction,
        "hz": hz,
        "by_solver": {},
    }
    with tempfile.TemporaryDirectory() as tmp:
        library, origin = compiled_library(tmp)
        solvers = ["numpy"] + (["compiled"] if library is not None else [])
        out.update({"library": origin, "solver": solvers[-1]})
        for name, data in (("moving", flux), ("rest", rest)):
            estimators = {s: nl.estimator() for s in solvers}
            for s, estimator in estimators.items():
                nlcompiled.attach(estimator, s, library)
            runs: dict[str, list] = {s: [] for s in solvers}
            for s in solvers:
                replay(estimators[s], data[:10], 1)  # warm: the pose found, first Jacobians made
            for j in range(loops):
                for s in solvers if j % 2 == 0 else solvers[::-1]:
                    runs[s].append(replay(estimators[s], data, 1))
            for s in solvers:
                cpu = np.concatenate([r[0] for r in runs[s]])
                result = {
                    "cpu_us": stats_us(cpu),
                    "not_converged": sum(r[2] for r in runs[s]),
                    "iterations_per_sample": sum(r[3] for r in runs[s]) / len(cpu),
                }
                if name == "moving":
                    wrench = runs[s][-1][1]
                    ok = np.all(np.isfinite(wrench), axis=1)
                    result["rms_error"] = np.sqrt(np.mean((wrench[ok] - truth[ok]) ** 2, axis=0)).tolist()
                out["by_solver"].setdefault(s, {})[name] = result
    out.update(out["by_solver"][out["solver"]])
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--quick", action="store_true", help="a few hundred samples (CI): the structure, not figures"
    )
    parser.add_argument(
        "--fraction", type=float, default=0.4, help="of the sensor's range on every axis (default 0.4)"
    )
    parser.add_argument("--hz", type=float, default=1.3, help="the load's frequency (default 1.3 Hz)")
    parser.add_argument(
        "--periods", type=int, default=13, help="periods of readings (default 13: 10 s at 1.3 Hz)"
    )
    parser.add_argument("--loops", type=int, default=5, help="times round the readings (default 5)")
    parser.add_argument("--cpu", type=int, default=None, help="pin to this core (default: the last one)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args()
    periods, loops = (2, 1) if args.quick else (args.periods, args.loops)
    cpu = pin_to_core(args.cpu)
    load = os.getloadavg()[0]
    r = measure(args.fraction, args.hz, periods, loops)
    r.update({"pinned_cpu": cpu, "load_1min": load, "quick": args.quick, "machine": machine()})
    if args.json:
        print(json.dumps(r, indent=2))
        return 0
    print(
        f"{r['machine']}, pinned to core {cpu}, load {load:.2f}; {r['samples']} readings x {loops} loops; "
        f"every axis at {args.fraction:.0%} of the range, {args.hz:g} Hz; compiled solver: {r['library']}"
    )
    for solver, runs in r["by_solver"].items():
        for name in ("moving", "rest"):
            s = runs[name]["cpu_us"]
            print(
                f"{solver:8s} {name:7s} mean {s['mean']:6.1f}  p50 {s['p50']:6.1f}  p99 {s['p99']:6.1f}  "
                f"max {s['max']:7.1f} us a sample; {runs[name]['iterations_per_sample']:.2f} iterations, "
                f"{runs[name]['not_converged']} not converged"
            )
        err = runs["moving"]["rms_error"]
        print(
            f"{solver:8s} moving: RMS error "
            + " ".join(f"{e:.3g}" for e in err)
            + " (N, Nm; target p99 <= 200 us)"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
