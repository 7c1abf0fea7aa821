"""A sensor warmed after its tare, through the daemon: what temperature compensation holds.

For each as-built part (tolerances as the default scene's, seeds the project uses nowhere
else), in the Earth's field, held still 30 deg from vertical:

1. Calibration by the procedure a user runs (`simulate_dataset`, then `calibrate`, linear):
   once at a constant 25 degC ("laws": the daemon has the physical laws only), once with the
   sensor's temperature cycling 24-36 degC during the run ("drift": the calibration measures
   each channel's drift too; docs/guide/calibration.md says what a real run must record).
2. The daemon (in process, virtual clock, 100 Hz) on the part at rest: 25 degC, a tare of
   100 samples at 5 s, then +10 K over 120 s as a hand warms a tool, held 60 s; then +15 K,
   beyond any span. The scene's laws act on the magnets, each chip (its own sensitivity and
   offset drift, drawn within the datasheet's bounds) and the silicone.
3. Measured on sensor1's wrench: over the 60 s held at +10 K, the median of each 1 s hold
   of unflagged samples (RMS over holds and the worst hold, per axis: the figure is within
   0.05 N and 2 mNm), the share of samples unflagged over the whole warming; at +15 K the
   share flagged `temperature` (all, to pass); and the 100 g validation at +10 K: a 100 g
   mass on a 50 mm rod in 8 directions (as the paper's Table II loads), RMS error per axis
   against Table II. The same run without temperature readings (`temperature_every = 0`) is
   the uncompensated baseline.

    python -m benchmarks.accuracy.warm            # 3 parts, about 10 minutes; writes nothing
    python -m benchmarks.accuracy.warm --quick    # 1 part, short profile (the test suite's run)
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from benchmarks.common import SENSOR1, daemon_config
from ftsensord.calibration.procedure import calibrate, simulate_dataset
from ftsensord.config.file import load_config
from ftsensord.protocol import wire
from ftsensord.sim import load_scene
from ftsensord.sim.loads import NO_LOAD, StaticLoad
from ftsensord.testing.harness import InProcess

#: The paper's Table II RMS errors (N x3, Nm x3).
TABLE_II = np.array([0.2338, 0.1136, 0.3775, 4.1e-3, 10.6e-3, 8.5e-3])
#: The figures to reach at rest: 0.05 N, 2 mNm (the aim near a motor, docs/results/accuracy.md).
REST_LIMIT = np.array([0.05, 0.05, 0.05, 2e-3, 2e-3, 2e-3])
SEEDS = (31, 32, 33)  # parts no other benchmark or test uses

PART = """version = 1
kind = "sensors"
external_field_ut = [22.3, 1.4, -42.6]
[[sensor]]
name = "sensor1"
addresses = [0x0C, 0x0D, 0x0E, 0x0F, 0x10, 0x11, 0x12, 0x13]
[sensor.tolerances]
magnet_position_mm = 0.15
magnet_remanence_pct = 3.0
chip_tilt_deg = 1.5
chip_gain_pct = 2.0
ring_radius_mm = 0.1
seed = {seed}
[sensor.temperature]
kind = "recorded"
times_s = {times}
celsius = {celsius}
"""


@dataclass(frozen=True)
class Profile:
    """The run's timing (s): tare at ``tare_s``; warm from ``warm_from_s`` over ``ramp_s``;
    hold ``hold_s`` at +10 K; then +15 K for ``beyond_s``."""

    tare_s: float = 5.0
    warm_from_s: float = 20.0
    ramp_s: float = 120.0
    hold_s: float = 60.0
    beyond_s: float = 10.0

    def scene(self, seed: int) -> str:
        t1 = self.warm_from_s + self.ramp_s
        t2 = t1 + self.hold_s
        times = [0.0, self.warm_from_s, t1, t2, t2 + 5.0]
        return PART.format(seed=seed, times=times, celsius=[25.0, 25.0, 35.0, 35.0, 40.0])


def validation_loads(mass_kg: float = 0.1, rod_m: float = 0.05) -> np.ndarray:
    """A mass on a rod along {0}'s z, pulled along 8 directions (N, Nm in {0}): the paper's
    validation loads, 100 g."""
    out = []
    for k in range(8):
        a = 2 * np.pi * k / 8
        f = mass_kg * 9.80665 * np.array([np.cos(a), np.sin(a), -0.5 if k % 2 else 0.5])
        out.append(np.concatenate([f, np.cross([0.0, 0.0, rod_m], f)]))
    return np.array(out)


def calibrate_part(seed: int, folder: Path, spanning: bool, quick: bool) -> Path:
    """The part calibrated by the procedure; ``spanning``: its temperature cycles 24-36 degC
    during the run, else 25 degC. The simulated robot does not dwell (a pose takes its
    readings' time: 20 samples 0.1 s, 100 samples 0.5 s), so the cycle is fast in scene time,
    20 poses a half period: the poses' temperatures span the range, unrelated to their order,
    and each pose's changes steadily (the rig takes the mean of its first and last reading)."""
    half_period_s = 2.0 if quick else 10.0
    times = [half_period_s * i for i in range(2000)]
    celsius = [24.0 if i % 2 else 36.0 for i in range(len(times))] if spanning else [25.0] * len(times)
    scene = folder / f"cal-scene-{seed}-{spanning}.toml"
    scene.write_text(PART.format(seed=seed, times=times, celsius=celsius))
    poses, samples = (80, 20) if quick else (193, 100)
    dataset = simulate_dataset(
        scene,
        "sensor1",
        "six-axis",
        poses=poses,
        validation_poses=0,
        samples=samples,
        seed=seed,
        sweeps=False,
    )
    cal, _ = calibrate(dataset, nonlinear=False)
    path = folder / f"cal-{seed}-{spanning}.json"
    cal.save(path)
    return path


def run(seed: int, cal: Path, folder: Path, profile: Profile, temperature_every: int) -> dict:
    """The warm run through the daemon; the figures (see the module's docstring)."""
    (folder / "scene.toml").write_text(profile.scene(seed))
    (folder / "ftsensord.toml").write_text(
        daemon_config(temperature_every=temperature_every)
        + f"""[[sensor]]
name = "sensor1"
addresses = [{SENSOR1}]
calibration = "{cal}"
"""
    )
    scene = load_scene(folder / "scene.toml")
    rig = InProcess(load_config(folder / "ftsensord.toml"), scene, subscribe=b"wrench/sensor1", seed=seed)
    d = rig.daemon
    times, values, flags = [], [], []

    def step(until: float) -> None:
        while rig.clock.now() < until:
            deadline = rig.clock.now() + d.period_s
            d.cycle()
            d.handle_control()
            rig.clock.wait_until(deadline)
            while rig.sub.poll(0):
                s = wire.decode(rig.sub.recv())
                times.append(s.t_mono)
                values.append(s.values)
                flags.append(s.flags)

    try:
        step(profile.tare_s)
        rig.req.send(json.dumps({"cmd": "tare", "samples": 100}).encode())
        step(profile.tare_s + 1.5)
        reply = json.loads(rig.req.recv()) if rig.req.poll(1000) else {"error": "no reply"}
        if not reply.get("ok"):
            raise RuntimeError(f"the tare failed: {reply}; flags before it: {sorted(set(flags))}")
        t1 = profile.warm_from_s + profile.ramp_s
        step(t1 + profile.hold_s)
        # 100 g validation at +10 K: each load held 1 s, the last 0.5 s of it judged.
        sensor = scene.sensors[0]
        errors = []
        for w in validation_loads():
            sensor.load = StaticLoad(w)
            start = len(values)
            step(rig.clock.now() + 1.0)
            held = np.array(values[start + 50 :])
            errors.append(np.median(held, axis=0) - w)
        sensor.load = NO_LOAD
        step(t1 + profile.hold_s + 5.0 + profile.beyond_s)
    finally:
        rig.close()
    t, v, f = np.array(times), np.array(values), np.array(flags)
    after_tare = t > profile.tare_s + 1.5
    hold = (t >= t1) & (t < t1 + profile.hold_s)
    medians, every = [], []  # each 1 s hold's median: of its unflagged samples, of all
    for k in range(int(profile.hold_s)):
        sel = hold & (t >= t1 + k) & (t < t1 + k + 1)
        every.append(np.median(v[sel], axis=0))
        if (sel & (f == 0)).any():
            medians.append(np.median(v[sel & (f == 0)], axis=0))
    medians = np.array(medians) if medians else np.full((1, 6), np.nan)
    warming = after_tare & (t < t1 + profile.hold_s)
    beyond = t > t1 + profile.hold_s + 5.0 + 1.0  # 1 s after reaching +15 K
    return {
        "rest_rms": np.sqrt(np.mean(medians**2, axis=0)),
        "rest_worst": np.abs(medians).max(axis=0),
        "rest_all_rms": np.sqrt(np.mean(np.array(every) ** 2, axis=0)),
        "holds": len(medians),
        "unflagged": float(np.mean(f[warming] == 0)),
        "samples": int(warming.sum()),
        "beyond_flagged": float(np.mean(f[beyond] & wire.FLAG_TEMPERATURE > 0)),
        "beyond_samples": int(beyond.sum()),
        "validation_rms": np.sqrt(np.mean(np.array(errors) ** 2, axis=0)),
    }


def fmt(v: np.ndarray) -> str:
    return " ".join(f"{x:.3f}" for x in v[:3]) + " N, " + " ".join(f"{x * 1e3:.2f}" for x in v[3:]) + " mNm"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="one part, a short profile")
    args = parser.parse_args(argv)
    profile = Profile(ramp_s=20.0, hold_s=10.0, beyond_s=3.0) if args.quick else Profile()
    seeds = SEEDS[:1] if args.quick else SEEDS
    ok = True
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for seed in seeds:
            for label, spanning, every in (("drift", True, 10), ("laws", False, 10), ("none", False, 0)):
                cal = calibrate_part(seed, folder, spanning, args.quick)
                r = run(seed, cal, folder, profile, every)
                print(
                    f"part {seed} {label:5s}: +10 K at rest, medians of {r['holds']} 1 s holds: "
                    f"RMS {fmt(r['rest_rms'])}; "
                    f"worst {fmt(r['rest_worst'])}; all samples' RMS {fmt(r['rest_all_rms'])}; "
                    f"unflagged {100 * r['unflagged']:.1f} % of {r['samples']}; "
                    f"+15 K flagged {100 * r['beyond_flagged']:.1f} % of {r['beyond_samples']}; "
                    f"100 g validation RMS {fmt(r['validation_rms'])} "
                    f"({'within' if np.all(r['validation_rms'] <= TABLE_II) else 'beyond'} Table II)"
                )
                if label == "drift":
                    ok &= bool(
                        np.all(r["rest_rms"] <= REST_LIMIT)
                        and r["unflagged"] >= 0.8
                        and r["beyond_flagged"] == 1.0
                        and np.all(r["validation_rms"] <= TABLE_II)
                    )
    print("figures met" if ok else "figures missed")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
