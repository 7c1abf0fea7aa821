"""The figures of docs/guide/clients.md, "How well it compensates": tests/test_gravity.py's
configurations run as the tests run them, their figures printed instead of asserted.

1. The realistic scene: sensor1 as built (config/scene-room.toml's tolerances, seed 1) in the
   Earth's field, calibrated there (60 fit, 20 validation, 12 no-load poses), a 50 g tool part;
   tared at a tilt, turned through 24 orientations, 10 samples each.
2. The nominal scene, both sensors and the tip, the same turning; then with a load on sensor1
   at 8 orientations.

Run from the repository root (about 20 s):

    python -m benchmarks.accuracy.gravity_figures
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from tests.test_daemon import LOAD
from tests.test_gravity import Turning, noise_sigma, orientations, realistic_run

MILLI = np.array([1e3] * 6)  # N, Nm -> mN, mNm


def fmt(x: np.ndarray, digits: int = 1) -> str:
    return (
        f"{', '.join(f'{v:.{digits}f}' for v in x[:3])} mN; {', '.join(f'{v:.{digits}f}' for v in x[3:])} mNm"
    )


def realistic(folder: Path) -> None:
    r = realistic_run(folder)
    sigma, swing = r["sigma"], np.ptp(r["raw"], axis=0)
    print("realistic scene, sensor1 compensated:")
    print(f"  noise bound sigma: {fmt(sigma * MILLI)}")
    print(f"  calibration's validation RMSE: {fmt(r['validation'] * MILLI)}")
    print(
        f"  samples flagged: {r['flagged']} of 240; largest sample: {(r['worst_sample'] / sigma).max():.1f} sigma"
    )
    print(f"  largest orientation mean: {fmt(r['worst_mean'] * MILLI)}")
    print(
        f"  uncompensated swing: {fmt(swing * MILLI, 0)} ({', '.join(f'{v:.0f}' for v in swing / sigma)} sigma)"
    )


def nominal(folder: Path) -> None:
    for sub in ("no-load", "load"):
        (folder / sub).mkdir()
    t = Turning(folder / "no-load")
    sigma = noise_sigma(t)
    t.turn(orientations(7)[3])
    t.cycles(3)
    assert t.tare()["ok"]
    worst_sample, worst_mean = dict.fromkeys(sigma, 0.0), dict.fromkeys(sigma, np.zeros(6))
    flagged = 0
    for R in orientations(24):
        t.turn(R)
        out = t.cycles(10)
        for topic, s in sigma.items():
            values = np.array([x.values for x in out[topic]])
            flagged += sum(x.flags != 0 for x in out[topic])
            worst_sample[topic] = max(worst_sample[topic], float(np.max(np.abs(values) / s)))
            worst_mean[topic] = np.maximum(worst_mean[topic], np.abs(values.mean(axis=0)))
    t.close()
    print(f"nominal scene, no load: samples flagged {flagged} of {240 * len(sigma)}")
    for topic in sigma:
        mean = fmt(worst_mean[topic] * MILLI)
        print(f"  {topic}: largest sample {worst_sample[topic]:.1f} sigma; largest mean {mean}")
    t = Turning(folder / "load", load=LOAD)
    worst, worst_raw = np.zeros(6), 0.0
    for R in orientations(8):
        t.turn(R)
        out = t.cycles(10)
        comp = np.mean([s.values for s in out["wrench/sensor1/compensated"]], axis=0)
        raw = np.mean([s.values for s in out["wrench/sensor1"]], axis=0)
        worst = np.maximum(worst, np.abs(comp - LOAD))
        worst_raw = max(worst_raw, float(np.max(np.abs(raw[:3] - LOAD[:3]))))
    t.close()
    print(f"nominal scene, load {LOAD} on sensor1, 8 orientations:")
    print(f"  compensated, largest error: {fmt(worst * MILLI)}; raw forces off by up to {worst_raw:.2f} N")


def main() -> int:
    with tempfile.TemporaryDirectory() as tmp:
        for name, run in (("realistic", realistic), ("nominal", nominal)):
            (Path(tmp) / name).mkdir()
            run(Path(tmp) / name)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
