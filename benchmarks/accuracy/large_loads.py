"""Check poses at large loads: does the calibration see what the paper's loads cannot?

Records the calibration plan as `ftsensord dataset` does (the default scene's as-built
sensor1, six-axis plan, with check poses: 1, 2 and 4 kg at the flange's centre) on parts
built as drawn, with magnets glued 2-7 deg tilted, and with silicone 30 % stiffer at range,
each for several seeds (the part's tolerances and the noise), fits each as `ftsensord
calibrate` does and prints, per part: the nonlinear model's flux residual on the check
poses (p50), its force error over the load (RMS), both estimators' RMSE there, and
whether the large-load warning (`calibration.largeloads`) was given.

    python -m benchmarks.accuracy.large_loads                 # docs/guide/calibration.md "Check poses" (~3 min)
    python -m benchmarks.accuracy.large_loads --quick         # one seed, 25 readings a pose (a test)
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass, replace

import numpy as np

from benchmarks.common import tilted
from ftsensord.calibration.procedure import calibrate, simulate_dataset, summary
from ftsensord.sim import default_scene

KINDS = ("as drawn", "magnets tilted", "silicone stiffening")


@dataclass
class Row:
    seed: int
    kind: str
    report: dict
    warned: bool  # the large-load warning was given
    summary: str


def run(seed: int, kind: str, *, samples: int, poses: int, validation: int, no_load: int, check: int) -> Row:
    scene = default_scene()
    sensor = scene.sensors[0]
    if kind == "magnets tilted":
        g = sensor.geometry
        sensor.geometry = replace(g, magnet_axis=tilted(g.magnet_axis, np.random.default_rng(seed)))
    elif kind == "silicone stiffening":
        sensor.stiffening = 0.3
    ds = simulate_dataset(
        scene,
        "sensor1",
        "six-axis",
        poses=poses,
        validation_poses=validation,
        samples=samples,
        seed=seed,
        no_load_poses=no_load,
        check_poses=check,
    )
    cal, _ = calibrate(ds)
    warned = (
        any("at large loads" in w for w in cal.nonlinear.warnings) if cal.nonlinear is not None else False
    )
    return Row(seed, kind, cal.report["large_loads"], warned, summary(cal))


def quick(seed: int = 1) -> list[Row]:
    """One seed of each kind with 25 readings a pose (and few validation and no-load poses)."""
    return [run(seed, k, samples=25, poses=193, validation=6, no_load=12, check=18) for k in KINDS]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="5,6,7")
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    t0 = time.monotonic()
    rows = (
        quick()
        if args.quick
        else [
            run(int(s), k, samples=100, poses=193, validation=60, no_load=24, check=24)
            for s in args.seeds.split(",")
            for k in KINDS
        ]
    )
    print(
        "| part | seed | residual p50 (uT) | force error / load | nonlinear RMSE Fx Fy Fz (N) "
        "| linear RMSE Fz (N) | warned |"
    )
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        ll = r.report
        nl = ll["nonlinear_rmse"]
        print(
            f"| {r.kind} | {r.seed} | {ll['nonlinear_residual_ut_p50']:.2f} | {ll['nonlinear_force_share']:.1%} | "
            f"{nl['Fx']:.3f} {nl['Fy']:.3f} {nl['Fz']:.3f} | {ll['linear_rmse']['Fz']:.2f} | "
            f"{'yes' if r.warned else 'no'} |"
        )
    print(
        f"{len(rows)} parts, {rows[0].report['poses']} check poses each (|F| to "
        f"{rows[0].report['largest_force_n']:.1f} N), {time.monotonic() - t0:.0f} s"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
