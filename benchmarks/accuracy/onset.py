"""A chip's sudden offset: how many samples pass the redundancy check before it is found.

A step of one chip's field (a steel splinter on its magnet, a chip's own offset jump),
random chip and direction, of each size asked, on the default scene's sensor1 at rest with
the packaged calibration, through the sensor's pipeline (`SensorPipeline.step`, linear, as
the daemon runs it): 10 clean samples, then the offset for ``--after`` samples; the flux
is the scene's plus Gaussian noise at the daemon's own channel sigma. Reported per size:
onsets, the samples after the onset that went out unflagged more than 5 sigma (of one
sample's wrench noise, any axis) from the truth, in how many onsets, the worst, and how
many samples after the onset the check first flagged (median, largest).

One sample's check lets a chip through while its drop is within the noise's 1e-9 point
plus the model's allowance (`processing.redundancy`): at 0.64 sigma of wrench per unit of
residual, a step in a chip's worst direction just under that limit moves the wrench ~5.7
sigma, noise adds to it, and the slow test (10 samples summed) needs a sample or two more.

    python -m benchmarks.accuracy.onset [--sizes-ut 20 35 50 80] [--onsets 60] [--after 30]
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from ftsensord.acquire.readings import Readings
from ftsensord.config.file import builtin_path, load_config
from ftsensord.processing.filters import WrenchFilter
from ftsensord.processing.pipeline import SensorPipeline, channel_sigma_t
from ftsensord.sim import default_scene

CLEAN = 10  # samples before the onset: the slow test's window full, as in a running daemon


def onsets(sizes_ut: list[float], count: int, after: int, seed: int = 0) -> dict[str, dict]:
    config = load_config(builtin_path("sim.toml"))
    s = config.sensors[0]
    scene = default_scene()
    sigma = channel_sigma_t(config.settings, len(s.addresses))
    truth = np.concatenate([scene.field_t(a, 0.0) for a in s.addresses])
    rng = np.random.default_rng(seed)

    def step(p: SensorPipeline, b: np.ndarray):
        return p.step(Readings.of_field(s.addresses, b))

    # One sample's wrench noise per axis, measured on the same pipeline at rest.
    p = SensorPipeline.build(s, WrenchFilter(), config.max_missing_chips, config.settings)
    p.tare(truth)
    rest = np.array([step(p, truth + rng.normal(0, 1, truth.size) * sigma).wrench for _ in range(2000)])
    noise = rest.std(axis=0)
    out = {}
    for size in sizes_ut:
        wrong, onsets_wrong, worst, first = 0, 0, 0.0, []
        for _ in range(count):
            p = SensorPipeline.build(s, WrenchFilter(), config.max_missing_chips, config.settings)
            p.tare(truth)
            chip, direction = rng.integers(len(s.addresses)), rng.normal(size=3)
            offset = np.zeros(truth.size)
            offset[3 * chip : 3 * chip + 3] = size * 1e-6 * direction / np.linalg.norm(direction)
            hits, found = 0, None
            for k in range(CLEAN + after):
                got = step(p, truth + rng.normal(0, 1, truth.size) * sigma + (offset if k >= CLEAN else 0.0))
                if k < CLEAN:
                    continue
                if got.flags:  # any flag warns the user (as benchmarks/accuracy/motor_close.py counts)
                    found = k - CLEAN if found is None else found
                    continue
                error = float(np.max(np.abs(got.wrench) / noise))
                if error > 5:
                    hits += 1
                    worst = max(worst, error)
            wrong += hits
            onsets_wrong += hits > 0
            first.append(after if found is None else found)
        out[f"{size:g} uT"] = {
            "onsets": count,
            "samples_after_each": after,
            "unflagged_beyond_5_sigma": wrong,
            "onsets_letting_one_through": onsets_wrong,
            "worst_sigma": round(worst, 2),
            "first_flagged_median": float(np.median(first)),
            "first_flagged_max": int(max(first)),
        }
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes-ut", type=float, nargs="+", default=[20, 35, 50, 80])
    parser.add_argument("--onsets", type=int, default=60)
    parser.add_argument("--after", type=int, default=30)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print(json.dumps(onsets(args.sizes_ut, args.onsets, args.after, args.seed), indent=1))


if __name__ == "__main__":
    main()
