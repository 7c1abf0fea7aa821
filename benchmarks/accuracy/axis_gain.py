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

    python -m benchmarks.accuracy.axis_gain [--parts 74 75 76]   # writes docs/results/axis-gain.md
    python -m benchmarks.accuracy.axis_gain --quick --out /tmp/axis-gain.md  # the page's structure
"""

from __future__ import annotations

import argparse
import contextlib
import io
import sys
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.accuracy.creep import scene_path
from benchmarks.common import QUICK_DATASET, RESULTS
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


def calibrate(seed: int, folder: Path, dataset_options: list[str]) -> Calibration:
    """Part ``seed`` calibrated by the two documented commands at their defaults (quick runs:
    ``dataset_options`` shrink the dataset, and the fit is kept whatever it gives)."""
    ds, cal = folder / f"ds-{seed}.json", folder / f"cal-{seed}.json"
    scene = scene_path(False, folder, seed)  # the default scene, sensor1 of this seed, no memory
    with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
        if (
            cli.main(
                ["dataset", "--scene", str(scene), "--sensor", "sensor1", "-o", str(ds), *dataset_options]
            )
            != 0
            or cli.main(
                ["calibrate", str(ds), "-o", str(cal), *(["--allow-poor-fit"] if dataset_options else [])]
            )
            != 0
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


def page(rows: list[str], parts: list[int]) -> str:
    """docs/results/axis-gain.md: the gains, a row a part and estimator."""
    return "\n".join(
        [
            "# A load along one axis: the static gain per axis",
            "",
            "What each estimator publishes over the load applied, for a load along one axis alone "
            "(1 N on a force axis, 50 mNm on a torque axis, each sign), through the daemon's pipeline "
            "on the scene's noiseless flux: 1 when the estimator reads a pure load right. Parts "
            f"{', '.join(map(str, parts))} (the default scene's sensor1 built with these tolerance seeds, "
            "in its room), each calibrated by `ftsensord dataset --scene S --sensor sensor1 -o ds.json` "
            "and `ftsensord calibrate ds.json -o cal.json` at their defaults; 12 loads a part and "
            "estimator. What it means: [estimators](../design/estimators.md#a-load-along-one-axis).",
            "",
            "| part | estimator | " + " | ".join(f"{a} (+ / -)" for a in AXES) + " |",
            "|---|---|" + "---|" * 6,
            *rows,
            "",
        ]
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", type=int, nargs="+", default=[74, 75, 76])
    parser.add_argument("--out", type=Path, default=RESULTS / "axis-gain.md")
    parser.add_argument(
        "--quick", action="store_true", help="one part, a small dataset: the page's structure"
    )
    args = parser.parse_args()
    parts = args.parts[:1] if args.quick else args.parts
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for seed in parts:
            cal = calibrate(seed, folder, QUICK_DATASET if args.quick else [])
            scene = load_scene(scene_path(False, folder, seed))
            assert isinstance(scene, PhysicalScene)
            for estimator in ("linear", "nonlinear"):
                if estimator == "nonlinear" and cal.nonlinear is None:
                    rows.append(f"| {seed} | nonlinear | not calibrated: {cal.report.get('nonlinear')} |")
                    continue
                g = gains(scene, cal, folder / f"cal-{seed}.json", estimator)
                cells = " | ".join(f"{g[a, 0]:.3f} / {g[a, 1]:.3f}" for a in range(6))
                rows.append(f"| {seed} | {estimator} | {cells} |")
    args.out.write_text(page(rows, parts))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
