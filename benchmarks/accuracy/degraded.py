"""Accuracy of degraded mode: the wrench from 7 or 6 of a sensor's 8 chips.

Records a calibration dataset on the simulated sensor (the paper's procedure, as
`ftsensord dataset`), fits it, and on the validation poses compares the RMSE per axis
of the full model with the degraded estimate for every single missing chip and every
pair of adjacent and of opposite chips. Run:

    python -m benchmarks.accuracy.degraded [--samples 100]
"""

from __future__ import annotations

import argparse
import itertools

import numpy as np

from ftsensord.calibration.fit import AXES, fit
from ftsensord.calibration.rig import record_dataset, simulate_sweeps
from ftsensord.model.geometry import SensorGeometry
from ftsensord.sim import VirtualClock, simulated_bus, two_sensor_scene
from ftsensord.sim.loads import StaticLoad, paper_plan


def rmse(errors: np.ndarray) -> np.ndarray:
    return np.sqrt(np.mean(errors**2, axis=0))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=100)
    args = parser.parse_args()
    scene = two_sensor_scene()
    addresses = scene.sensors[0].addresses
    bus = simulated_bus(scene, clock=VirtualClock(), seed=1)
    ds = record_dataset(
        bus,
        addresses,
        paper_plan("six-axis"),
        lambda w: scene.set_load(0, StaticLoad(w)),
        samples=args.samples,
    )
    ds.sweeps = simulate_sweeps(addresses, SensorGeometry.ring(), samples=args.samples)
    model = fit(ds).model
    val = ds.select(ds.split == "validation")
    rows = [("all 8 chips, K A", rmse(model.wrench(val.flux_t) - val.wrench))]
    all_chips = np.ones(8, dtype=bool)
    rows.append(
        (
            "all 8 chips, K pinv(H)",
            rmse(np.array([model.wrench_from(b, all_chips) for b in val.flux_t]) - val.wrench),
        )
    )

    def degraded(missing: tuple[int, ...]) -> np.ndarray:
        chips = all_chips.copy()
        chips[list(missing)] = False
        return rmse(np.array([model.wrench_from(b, chips) for b in val.flux_t]) - val.wrench)

    singles = np.array([degraded((i,)) for i in range(8)])
    adjacent = np.array([degraded((i, (i + 1) % 8)) for i in range(8)])
    opposite = np.array([degraded((i, i + 4)) for i in range(4)])
    rows += [
        ("one missing, mean of 8", singles.mean(0)),
        ("one missing, worst", singles.max(0)),
        ("two adjacent, mean of 8", adjacent.mean(0)),
        ("two adjacent, worst", adjacent.max(0)),
        ("two opposite, mean of 4", opposite.mean(0)),
        ("two opposite, worst", opposite.max(0)),
    ]
    print(f"{len(val)} validation poses, {args.samples} samples a pose")
    print(
        "| chips used | " + " | ".join(f"{a} ({'N' if k < 3 else 'mNm'})" for k, a in enumerate(AXES)) + " |"
    )
    print("|---|" + "---|" * 6)
    for label, r in rows:
        print(
            f"| {label} | "
            + " | ".join(f"{v:.4f}" if k < 3 else f"{v * 1e3:.2f}" for k, v in enumerate(r))
            + " |"
        )
    three = list(itertools.combinations(range(8), 3))
    print(f"(three or more missing: refused, flagged invalid; {len(three)} such sets of three)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
