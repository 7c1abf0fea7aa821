"""What each sample's sigma costs the daemon: `SensorPipeline.step` with its `uncertainty`
and without, per estimator, on a held load and on a load that changes every sample.

The packaged configuration's sensor1 and calibration, its flux from the default scene with
0.1 uT of noise, the pipeline as the daemon builds it (`SensorPipeline.build`, the
temperature stage off: it is the same with and without the sigma). A held load keeps the
nonlinear estimator's noise map; a load drawn anew each sample (50 loads in turn, |F| to
1.7 N, torques to 35 mNm) moves its pose past the solve's Jacobian reuse bound at nearly
every sample, so the map is made again from the solve's new Jacobian: the worst case. CPU
time of ``--samples`` steps, the best of ``--rounds`` (taken without and with the sigma in turn).

    python -m benchmarks.performance.sigma_cost [--samples 4000] [--rounds 3]  # docs/results/sigma-cost.md
    python -m benchmarks.performance.sigma_cost --quick --out /tmp/sigma-cost.md  # the page's structure
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.common import RESULTS
from ftsensord.acquire.readings import Readings
from ftsensord.config.file import load_config
from ftsensord.processing.filters import WrenchFilter
from ftsensord.processing.pipeline import SensorPipeline
from ftsensord.sim.loads import StaticLoad
from ftsensord.sim.scene import default_scene

#: Loads a sample goes through in turn when the load changes every sample.
LOADS = 50


def cycles(moving: bool) -> list[Readings]:
    """The sensor's readings: one held load, or `LOADS` drawn at random (seeded)."""
    scene, rng = default_scene(), np.random.default_rng(1)
    sensor = scene.sensors[0]
    out = []
    for _ in range(LOADS if moving else 1):
        w = (
            np.r_[rng.uniform(-1, 1, 3), rng.uniform(-0.02, 0.02, 3)]
            if moving
            else np.array([1.0, 0, 0, 0, 0, 0])
        )
        scene.set_load(sensor.name, StaticLoad(w))
        flux = np.concatenate([scene.field_t(a, 100.0) for a in sensor.addresses])
        out.append(Readings.of_field(sensor.addresses, flux + rng.normal(0, 1e-7, flux.size)))
    return out


def step_us(estimator: str, sigma: bool, readings: list[Readings], samples: int) -> float:
    """CPU time (us) of one `SensorPipeline.step`, averaged over ``samples``."""
    config = load_config().sensors[0]
    pipeline = SensorPipeline.build(config, WrenchFilter(), 2, thermal=False, rate_hz=100.0)
    pipeline.use(estimator)
    if not sigma:
        pipeline.uncertainty = None
    for r in readings[:10]:  # the first steps build the maps and caches: not the steady cost
        pipeline.step(r)
    began = time.process_time()
    for i in range(samples):
        pipeline.step(readings[i % len(readings)])
    return (time.process_time() - began) / samples * 1e6


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=4000)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--out", type=Path, default=RESULTS / "sigma-cost.md")
    parser.add_argument("--quick", action="store_true", help="200 samples, one round: the page's structure")
    args = parser.parse_args()
    samples, rounds = (200, 1) if args.quick else (args.samples, args.rounds)
    rows = []
    for estimator in ("linear", "nonlinear"):
        for moving in (False, True):
            readings = cycles(moving)
            # The rounds without and with the sigma in turn, so that a change in the host's speed
            # meets both: all of one then all of the other made the share a difference of two
            # moments (the nonlinear held load's came out above the moving one's).
            times: dict[bool, list[float]] = {False: [], True: []}
            for _ in range(rounds):
                for sigma in (False, True):
                    times[sigma].append(step_us(estimator, sigma, readings, samples))
            off, on = min(times[False]), min(times[True])
            load = "a new one every sample" if moving else "held"
            rows.append(f"| {estimator} | {load} | {off:.1f} | {on:.1f} | {on - off:.1f} |")
    args.out.write_text(
        "\n".join(
            [
                "# What each sample's sigma costs",
                "",
                "The CPU time of `SensorPipeline.step` (the daemon's per-sensor step) with each sample's "
                "sigma and without it, per estimator, on a held load and on a load that changes every "
                "sample (the nonlinear noise map then made again from the solve's new Jacobian at nearly "
                "every sample: the worst case). The packaged configuration's sensor1 and calibration, the "
                f"default scene's flux with 0.1 uT of noise; {samples} steps a case, the best of {rounds} "
                "rounds, taken without and with the sigma in turn. What the sigma holds: "
                "[estimators](../design/estimators.md#each-samples-sigma); the "
                "daemon's whole cycle: [the trade-off](tradeoff.md).",
                "",
                "| estimator | load | step without the sigma (us) | with (us) | the sigma's share (us) |",
                "|---|---|---|---|---|",
                *rows,
                "",
            ]
        )
    )
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
