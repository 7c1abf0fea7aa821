"""How often the chips' own noise alone puts a wrench more than 5 sigma from its mean.

A wrench is K A times 24 readings, each the true field plus the chip's Gaussian noise,
rounded to the LSB. At the paper's settings (GAIN_SEL 0, RES 3) the LSB is three times the
chip's noise, so a reading is mostly one of two or three levels and a wrench axis that a few
channels dominate (Mz: the chips' X channels) is a sum of a few discrete steps: heavier tails
than a Gaussian's. This draws the readings of a scene's chips at rest (true field at t = 0,
noise and LSB as the emulator makes them) and counts, per wrench stream, samples beyond
``--sigma`` on any axis, beside a Gaussian's count; ``--res`` redoes it at another RES
(range and conversion time do not change with RES; docs/results/reliability.md, "Noise tails").

    python -m benchmarks.accuracy.noise_tails [--samples 2000000] [--res 3 2 1]
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from pathlib import Path

import numpy as np

from benchmarks.common import tail_rate, wrench_noise
from ftsensord.config.file import builtin_path, load_config
from ftsensord.sim import default_scene, load_scene


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=2_000_000)
    parser.add_argument("--sigma", type=float, default=5.0)
    parser.add_argument(
        "--res", type=int, nargs="+", default=[3], help="RES for X, Y and Z (default: 3, the paper's)"
    )
    parser.add_argument("--scene", type=Path, default=None, help="a scene file (default: the default scene)")
    args = parser.parse_args()
    config = load_config(builtin_path("sim.toml"))
    scene = load_scene(args.scene) if args.scene else default_scene()
    gauss = 6 * math.erfc(args.sigma / math.sqrt(2))  # any of 6 independent Gaussian axes
    print(
        f"{args.samples} samples a stream, at rest; beyond {args.sigma:g} sigma on any axis, per million samples "
        f"(a Gaussian: {gauss * 1e6:.2f})"
    )
    for res in args.res:
        settings = dataclasses.replace(config.settings, res_x=res, res_y=res, res_z=res)
        for topic, w in wrench_noise(config, scene, args.samples, settings).items():
            kurtosis = np.mean((w / w.std(axis=0)) ** 4, axis=0)
            print(
                f"RES {res} {topic:15s} sigma (N; mNm) {' '.join(f'{v:.4f}' for v in w.std(axis=0)[:3])}; "
                f"{' '.join(f'{v * 1e3:.2f}' for v in w.std(axis=0)[3:])}  kurtosis "
                f"{' '.join(f'{k:.2f}' for k in kurtosis)}  beyond: {tail_rate(w, args.sigma) * 1e6:.1f}"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
