"""Small motors a few cm away, inside the distance docs/results/accuracy.md says to keep: how many
samples go out unflagged and how wrong.

A point dipole (`[[stray_source]]`'s `StraySource`) at random placements and moments near
the default scene's sensor1 (packaged calibration, `stray_field` at its default), switched
on after the tare, under a random static load within half the calibration's; each
placement 20 samples through the sensor's pipeline, the flux the scene's plus Gaussian
noise at the daemon's channel sigma. Reported per estimator, distance and moment: samples
without any flag beyond 0.05 N or 2 mNm from the load, and the worst force and moment errors
among them (each its own largest).

    python -m benchmarks.accuracy.motor_close [--placements 16]
"""

from __future__ import annotations

import argparse
import dataclasses
import json

import numpy as np

from ftsensord.acquire.readings import Readings
from ftsensord.config.file import builtin_path, load_config
from ftsensord.processing.filters import WrenchFilter
from ftsensord.processing.pipeline import SensorPipeline, channel_sigma_t
from ftsensord.sim import default_scene
from ftsensord.sim.loads import StaticLoad
from ftsensord.sim.physics import StraySource

CASES = ((0.03, 0.1), (0.04, 0.1), (0.05, 0.1), (0.04, 0.02))  # (distance m, moment A m^2)
LOAD = np.array([0.5, -0.3, 0.8, 0.02, -0.01, 0.015])  # N, Nm; times a uniform draw in [-1, 1]


def run(placements: int, samples: int = 20, seed: int = 7) -> list[dict]:
    config = load_config(builtin_path("sim.toml"))
    s = config.sensors[0]
    sigma = channel_sigma_t(config.settings, len(s.addresses))
    rng = np.random.default_rng(seed)
    out = []
    for estimator in ("linear", "nonlinear"):
        sensor = dataclasses.replace(s, estimator=estimator)
        for r, m in CASES:
            wrong, worst_n, worst_nm = 0, 0.0, 0.0
            for _ in range(placements):
                where, moment = rng.normal(size=3), rng.normal(size=3)
                scene = default_scene()  # the motor off until t = 0.01 s
                scene.stray_sources.append(
                    StraySource(
                        where / np.linalg.norm(where) * r,
                        moment / np.linalg.norm(moment) * m,
                        np.array([0.0, 0.01]),
                        np.array([0.0, 1.0]),
                    )
                )
                load = LOAD * rng.uniform(-1, 1)
                p = SensorPipeline.build(sensor, WrenchFilter(), config.max_missing_chips, config.settings)
                scene.set_load(0, StaticLoad(np.zeros(6)))
                p.tare(np.concatenate([scene.field_t(a, 0.0) for a in s.addresses]))
                scene.set_load(0, StaticLoad(load))
                b = np.concatenate([scene.field_t(a, 1.0) for a in s.addresses])
                for _ in range(samples):
                    got = p.step(Readings.of_field(s.addresses, b + rng.normal(0, 1, b.size) * sigma))
                    e = np.abs(got.wrench - load)
                    if got.flags == 0 and (e[:3].max() > 0.05 or e[3:].max() > 2e-3):  # any flag warns
                        wrong += 1
                        worst_n, worst_nm = (
                            max(worst_n, float(e[:3].max())),
                            max(worst_nm, float(e[3:].max() * 1e3)),
                        )
            out.append(
                {
                    "estimator": estimator,
                    "distance_cm": r * 100,
                    "moment_am2": m,
                    "samples": placements * samples,
                    "unflagged_wrong": wrong,
                    "worst_n": round(worst_n, 3),
                    "worst_mnm": round(worst_nm, 1),
                }
            )
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--placements", type=int, default=16)
    args = parser.parse_args()
    for row in run(args.placements):
        print(json.dumps(row))


if __name__ == "__main__":
    main()
