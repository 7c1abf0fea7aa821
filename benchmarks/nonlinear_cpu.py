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
does not count) gives mean, p50, p99 and max. The same readings at rest (the load's mean,
zero) give the figure the at-rest benchmark (`cycle_cpu.py`) reports, for comparison.
Accuracy: each estimate's wrench K (xi - xi0) against the scene's load (RMS per axis),
and how many did not converge (the daemon falls back to the linear estimate for those).

    python benchmarks/nonlinear_cpu.py                  # the docs' figures (about 20 s)
    python benchmarks/nonlinear_cpu.py --quick --json   # CI: a few hundred samples
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import time
from typing import Any

import numpy as np

from ftsensord.model.linear import SENSOR_RANGE
from ftsensord.model.nonlinear import NonlinearEstimator
from ftsensord.service.config import builtin_path, load_config
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


def replay(estimator: NonlinearEstimator, flux: np.ndarray, loops: int) -> tuple[np.ndarray, np.ndarray, int, int]:
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
    return {"mean": float(us.mean()), "p50": float(np.percentile(us, 50)), "p99": float(np.percentile(us, 99)),
            "max": float(us.max())}


def measure(fraction: float, hz: float, periods: int, loops: int) -> dict[str, Any]:
    config = load_config(builtin_path("sim.toml"))
    nl = config.sensors[0].calibration.nonlinear
    assert nl is not None  # the packaged calibrations have one
    flux, truth = readings(fraction, hz, periods)
    rest, _ = readings(0.0, hz, periods, seed=1)
    out: dict[str, Any] = {"samples": len(flux), "loops": loops, "fraction": fraction, "hz": hz}
    for name, data in (("moving", flux), ("rest", rest)):
        estimator = nl.estimator()
        replay(estimator, data[:10], 1)  # warm: the pose found, first Jacobians made
        cpu, wrench, failed, iterations = replay(estimator, data, loops)
        out[name] = {"cpu_us": stats_us(cpu), "not_converged": failed,
                     "iterations_per_sample": iterations / len(cpu)}
        if name == "moving":
            ok = np.all(np.isfinite(wrench), axis=1)
            out[name]["rms_error"] = np.sqrt(np.mean((wrench[ok] - truth[ok]) ** 2, axis=0)).tolist()
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a few hundred samples (CI): the structure, not figures")
    parser.add_argument("--fraction", type=float, default=0.4, help="of the sensor's range on every axis (default 0.4)")
    parser.add_argument("--hz", type=float, default=1.3, help="the load's frequency (default 1.3 Hz)")
    parser.add_argument("--periods", type=int, default=13, help="periods of readings (default 13: 10 s at 1.3 Hz)")
    parser.add_argument("--loops", type=int, default=5, help="times round the readings (default 5)")
    parser.add_argument("--cpu", type=int, default=None, help="pin to this core (default: the last one)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args()
    periods, loops = (2, 1) if args.quick else (args.periods, args.loops)
    cpu = args.cpu if args.cpu is not None else max(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {cpu})
    load = os.getloadavg()[0]
    r = measure(args.fraction, args.hz, periods, loops)
    r.update({"pinned_cpu": cpu, "load_1min": load, "quick": args.quick,
              "machine": f"{os.cpu_count()}-core {platform.machine()}, Python {platform.python_version()}"})
    if args.json:
        print(json.dumps(r, indent=2))
        return 0
    print(f"{r['machine']}, pinned to core {cpu}, load {load:.2f}; {r['samples']} readings x {loops} loops; "
          f"every axis at {args.fraction:.0%} of the range, {args.hz:g} Hz")
    for name in ("moving", "rest"):
        s = r[name]["cpu_us"]
        print(f"{name:7s} mean {s['mean']:6.1f}  p50 {s['p50']:6.1f}  p99 {s['p99']:6.1f}  max {s['max']:7.1f} us a sample; "
              f"{r[name]['iterations_per_sample']:.2f} iterations, {r[name]['not_converged']} not converged")
    err = r["moving"]["rms_error"]
    print("moving: RMS error " + " ".join(f"{e:.3g}" for e in err) + " (N, Nm; target p99 <= 200 us)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
