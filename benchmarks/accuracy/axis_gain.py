"""How each estimator reads a load along one axis alone: the static gain per axis.

For each part (the default scene's room, sensor1 built with tolerance seed ``--parts``, seeds
no other benchmark draws), the documented commands calibrate it at their defaults
(``ftsensord dataset --scene S --sensor sensor1 -o ds.json``, ``ftsensord calibrate ds.json -o
cal.json``). Then the daemon's own processing (`SensorPipeline` built from that calibration
file, fed the scene's noiseless flux as the reader hands a clean cycle over, tared at no load)
reads a load along each axis alone, both signs: 1 N on a force axis, 50 mNm on a torque axis
(inside the calibration's 50 g and 200 g poses' span). The gain is the published axis over the
applied one: 1 when the estimator reads a pure load right. The paper's `K A` is fitted to twists
estimated through the chips' position maps, then to the poses' wrenches, whose forces and
torques always come together (a mass on a rod): a load along one axis alone is outside what
the fit saw, which is where a linear model's compromise shows.

    python -m benchmarks.accuracy.axis_gain [--parts 74 75 76]

Figures in docs/design/estimators.md ("A load along one axis").
"""

from __future__ import annotations

import argparse
import contextlib
import io
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.accuracy.creep import scene_path
from benchmarks.common import machine
from ftsensord import cli
from ftsensord.acquire.readings import Readings
from ftsensord.calibration.calfile import Calibration
from ftsensord.config.sensors import SensorConfig
from ftsensord.processing.filters import WrenchFilter
from ftsensord.processing.pipeline import SensorPipeline
from ftsensord.sim import load_scene
from ftsensord.sim.loads import StaticLoad
from ftsensord.sim.physics import PhysicalScene

AXES = ("Fx", "Fy", "Fz", "Mx", "My", "Mz")
#: The load along each axis: 1 N, 50 mNm (the 200 g poses reach 2 N and 0.2 Nm together).
SIZE = np.array([1.0, 1.0, 1.0, 0.05, 0.05, 0.05])
#: When the scene is read (s): after the scene's start, any load long in place.
AT_S = 100.0


def calibrate(seed: int, folder: Path) -> Calibration:
    """Part ``seed`` calibrated by the two documented commands at their defaults."""
    ds, cal = folder / f"ds-{seed}.json", folder / f"cal-{seed}.json"
    scene = scene_path(False, folder, seed)  # the default scene, sensor1 of this seed, no memory
    with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
        if (
            cli.main(["dataset", "--scene", str(scene), "--sensor", "sensor1", "-o", str(ds)]) != 0
            or cli.main(["calibrate", str(ds), "-o", str(cal)]) != 0
        ):
            raise SystemExit(f"part {seed}: the documented commands failed")
    return Calibration.load(cal)


def gains(scene: PhysicalScene, cal: Calibration, path: Path, estimator: str) -> np.ndarray:
    """(6, 2) gains, each axis at + and - its `SIZE`, through the daemon's pipeline."""
    sensor = scene.sensors[0]
    config = SensorConfig(sensor.name, sensor.addresses, path, cal, "sensor1", estimator=estimator)
    pipeline = SensorPipeline.build(config, WrenchFilter(), 2, thermal=False, rate_hz=100.0)

    def flux(w: np.ndarray) -> np.ndarray:
        scene.set_load(sensor.name, StaticLoad(w))
        return np.concatenate([scene.field_t(a, AT_S) for a in sensor.addresses])

    pipeline.tare(flux(np.zeros(6)))
    out = np.empty((6, 2))
    for axis in range(6):
        for k, sign in enumerate((1.0, -1.0)):
            w = np.zeros(6)
            w[axis] = sign * SIZE[axis]
            out[axis, k] = pipeline.step(Readings.of_field(sensor.addresses, flux(w))).wrench[axis] / w[axis]
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", type=int, nargs="+", default=[74, 75, 76])
    args = parser.parse_args()
    began = time.monotonic()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for seed in args.parts:
            cal = calibrate(seed, folder)
            scene = load_scene(scene_path(False, folder, seed))
            assert isinstance(scene, PhysicalScene)
            for estimator in ("linear", "nonlinear"):
                if estimator == "nonlinear" and cal.nonlinear is None:
                    rows.append(f"| {seed} | nonlinear | not calibrated: {cal.report.get('nonlinear')} |")
                    continue
                g = gains(scene, cal, folder / f"cal-{seed}.json", estimator)
                cells = " | ".join(f"{g[a, 0]:.3f} / {g[a, 1]:.3f}" for a in range(6))
                rows.append(f"| {seed} | {estimator} | {cells} |")
    print("| part | estimator | " + " | ".join(f"{a} (+ / -)" for a in AXES) + " |")
    print("|---|---|" + "---|" * 6)
    print("\n".join(rows))
    print(
        f"\n{len(args.parts)} parts, 12 loads each, noiseless flux; {time.monotonic() - began:.0f} s on a "
        f"{machine()} host, {time.strftime('%Y-%m-%d', time.gmtime())}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
