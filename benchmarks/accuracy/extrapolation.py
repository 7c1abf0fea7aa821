"""How far beyond its calibration's loads the linear (K A) model holds.

Loads the packaged calibration of the default scene's sensor1, applies random wrenches
whose largest axis is s times the calibration's `wrench_range` on that axis (the rest in
proportion), and prints the linear model's RMSE per axis as a fraction of s x range: the
error relative to the load's size. The physics is noiseless, so this is the model's
error alone. The daemon flags a linear estimate beyond `EXTRAPOLATION_MARGIN` x range
`extrapolated` (ftsensord/processing/pipeline.py); this table is where that number comes from. Run:

    python -m benchmarks.accuracy.extrapolation [--loads 200]
"""

from __future__ import annotations

import argparse

import numpy as np

from ftsensord.calibration.calfile import Calibration
from ftsensord.calibration.fit import AXES
from ftsensord.config.file import builtin_path
from ftsensord.sim.loads import StaticLoad
from ftsensord.sim.scene import default_scene

SCALES = (0.5, 1.0, 1.5, 2.0, 3.0, 5.0, 10.0)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--loads", type=int, default=200, help="random loads per scale")
    args = parser.parse_args()
    cal = Calibration.load(builtin_path("sim-sensor1.json"))
    assert cal.wrench_range is not None
    scene = default_scene()  # the room and part the calibration was fitted on
    rng = np.random.default_rng(0)
    relative = {}
    for s in SCALES:
        errors = []
        for _ in range(args.loads):
            d = rng.normal(size=6)
            w = d / np.max(np.abs(d) / cal.wrench_range) * s
            scene.set_load("sensor1", StaticLoad(w))
            b = np.concatenate([scene.field_t(a, 0.0) for a in cal.addresses])
            errors.append(cal.model.wrench(b) - w)
        relative[s] = np.sqrt(np.mean(np.square(errors), axis=0)) / (s * cal.wrench_range)
    print("| load / wrench_range | " + " | ".join(AXES) + " | largest growth against 1x |")
    print("|---" * (len(AXES) + 2) + "|")
    for s, e in relative.items():
        cells = " | ".join(f"{100 * x:.1f} %" for x in e)
        print(f"| {s:g}x | {cells} | {np.max(e / relative[1.0]):.2f}x |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
