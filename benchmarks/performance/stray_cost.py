"""What the stray stage (`stray_field = "world"`) costs a sample, per sensor: `turn_to`,
`apply` and `learn` on a correcting stage, the orientation changing every 100 samples.

    python -m benchmarks.performance.stray_cost            # 20000 samples, the first 1000 left out
"""

from __future__ import annotations

import time

import numpy as np

from ftsensord.calibration.calfile import Calibration
from ftsensord.chip import mlx90393 as mlx
from ftsensord.config.file import builtin_path
from ftsensord.model import se3
from ftsensord.processing.pipeline import channel_sigma_t
from ftsensord.processing.stray import WorldGradient


def main() -> int:
    cal = Calibration.load(builtin_path("sim-sensor1.json"))
    stage = WorldGradient(cal.model, channel_sigma_t(mlx.Settings(), 8))
    rng = np.random.default_rng(0)
    turns = [se3.exp_so3(v) for v in rng.normal(size=(20, 3))]
    b = cal.model.zero + rng.normal(size=24) * 2e-6
    stage.turn_to(turns[0])
    stage.tared(b)
    took = []
    for k in range(20000):
        t0 = time.perf_counter()
        stage.turn_to(turns[(k // 100) % len(turns)])
        stage.apply(b)
        stage.learn(b)
        took.append(time.perf_counter() - t0)
    us = np.array(took[1000:]) * 1e6
    print(
        f"stray stage, a sample: p50 {np.percentile(us, 50):.1f} us, p99 {np.percentile(us, 99):.1f} us, "
        f"mean {us.mean():.1f} us ({len(us)} samples; correcting: {stage.correcting})"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
