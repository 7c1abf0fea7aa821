"""How often the chips' own noise alone puts a wrench more than 5 sigma from its mean.

A wrench is K A times 24 readings, each the true field plus the chip's Gaussian noise,
rounded to the LSB. At the paper's settings (GAIN_SEL 0, RES 3) the LSB is three times the
chip's noise, so a reading is mostly one of two or three levels and a wrench axis that a few
channels dominate (Mz: the chips' X channels) is a sum of a few discrete steps: heavier tails
than a Gaussian's. This draws the readings of a scene's chips at rest (true field at t = 0,
noise and LSB as the emulator makes them) and counts, per wrench stream, samples beyond
``--sigma`` on any axis, beside a Gaussian's count; ``--res`` redoes it at another RES
(range and conversion time do not change with RES; docs/results/reliability.md, "Noise tails").

    python benchmarks/noise_tails.py [--samples 2000000] [--res 3 2 1]
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from pathlib import Path

import numpy as np

from ftsensord.chip import mlx90393 as mlx
from ftsensord.model import se3
from ftsensord.config.file import Config, builtin_path, load_config
from ftsensord.sim import NoiseModel
from ftsensord.sim import default_scene
from ftsensord.sim import load_scene
from ftsensord.sim.chip import FieldSource

CHUNK = 200_000  # samples drawn at once: 200,000 x 24 doubles, 38 MB


def wrench_noise(config: Config, scene: FieldSource, samples: int, settings: mlx.Settings | None = None,
                 seed: int = 0) -> dict[str, np.ndarray]:
    """Per wrench stream (``wrench/<sensor>``, ``wrench/tip`` when the tool has poses), the
    deviation of ``samples`` simulated wrenches from their mean (samples, 6; N, Nm)."""
    settings = settings or config.settings
    noise = NoiseModel()
    rng = np.random.default_rng(seed)
    out: dict[str, np.ndarray] = {}
    for s in config.sensors:
        field_ut = np.concatenate([np.asarray(scene.field_t(a, 0.0)) for a in s.addresses]) * 1e6
        sigma_ut = np.tile([noise.sigma_ut(a, settings.tconvm_us()) for a in "xyz"], len(s.addresses))
        lsb_ut = np.tile([settings.sensitivity_ut(a) for a in "xyz"], len(s.addresses))
        KA = s.calibration.model.KA
        chunks = []
        for n in [CHUNK] * (samples // CHUNK) + [samples % CHUNK]:
            readings = np.round((field_ut + rng.standard_normal((n, len(field_ut))) * sigma_ut) / lsb_ut) * lsb_ut
            chunks.append(readings * 1e-6 @ KA.T)
        w = np.concatenate(chunks)
        out[f"wrench/{s.name}"] = w - w.mean(axis=0)
    if config.tool_poses:
        out["wrench/tip"] = sum(out[f"wrench/{n}"] @ se3.wrench_transform(T).T for n, T in config.tool_poses.items())
    return out


def tail_rate(deviations: np.ndarray, sigmas: float) -> float:
    """The share of samples beyond ``sigmas`` of their own spread on any axis."""
    return float(np.mean(np.max(np.abs(deviations) / deviations.std(axis=0), axis=1) > sigmas))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=2_000_000)
    parser.add_argument("--sigma", type=float, default=5.0)
    parser.add_argument("--res", type=int, nargs="+", default=[3], help="RES for X, Y and Z (default: 3, the paper's)")
    parser.add_argument("--scene", type=Path, default=None, help="a scene file (default: the default scene)")
    args = parser.parse_args()
    config = load_config(builtin_path("sim.toml"))
    scene = load_scene(args.scene) if args.scene else default_scene()
    gauss = 6 * math.erfc(args.sigma / math.sqrt(2))  # any of 6 independent Gaussian axes
    print(f"{args.samples} samples a stream, at rest; beyond {args.sigma:g} sigma on any axis, per million samples "
          f"(a Gaussian: {gauss * 1e6:.2f})")
    for res in args.res:
        settings = dataclasses.replace(config.settings, res_x=res, res_y=res, res_z=res)
        for topic, w in wrench_noise(config, scene, args.samples, settings).items():
            kurtosis = np.mean((w / w.std(axis=0)) ** 4, axis=0)
            print(f"RES {res} {topic:15s} sigma (N; mNm) {' '.join(f'{v:.4f}' for v in w.std(axis=0)[:3])}; "
                  f"{' '.join(f'{v * 1e3:.2f}' for v in w.std(axis=0)[3:])}  kurtosis "
                  f"{' '.join(f'{k:.2f}' for k in kurtosis)}  beyond: {tail_rate(w, args.sigma) * 1e6:.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
