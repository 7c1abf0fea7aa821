"""Coverage of each sample's sigma: the fraction of samples whose error against the scene's
truth lies within 1 and 2 sigma, per axis, at rest and under held loads.

For each part (the default scene's room, sensor1 built with tolerance seed ``--parts``, seeds
no test uses), the documented commands calibrate it: ``ftsensord dataset`` (its defaults, noise
seed = the part's) and ``ftsensord calibrate --linear-only``. Then a daemon on that scene
(in process, virtual clock, the packaged settings, averaging and low-pass off) tares at rest
(100 samples, the default) and publishes ``--samples`` samples at rest and at each of ``--loads``
random held loads within the calibration's range (|F| up to 2 N, torques to 0.04 Nm: the
validation poses' span); each sample's error is the wrench minus the truth, the truth being
the held load itself (the tare at no load). Run:

    python -m benchmarks.accuracy.coverage [--parts 71 72 73] [--loads 8] [--samples 300]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from ftsensord.config.file import load_config
from ftsensord.protocol import wire
from ftsensord.sim import load_scene
from ftsensord.sim.loads import StaticLoad
from ftsensord.sim.scene import default_scene_path
from ftsensord.testing.harness import InProcess

AXES = ("Fx", "Fy", "Fz", "Mx", "My", "Mz")


def scene_text(seed: int, load: list[float] | None) -> str:
    """The default scene with sensor1 made with tolerance seed ``seed`` (under ``load``)."""
    text = default_scene_path().read_text().replace("seed = 1 ", f"seed = {seed} ", 1)
    if load is not None:
        table = f'[sensor.load]\nkind = "static"\nwrench = {list(load)}\n'
        text = text.replace("[sensor.orientation]", table + "[sensor.orientation]", 1)
    return text


def calibrate(folder: Path, seed: int) -> Path:
    (folder / "scene.toml").write_text(scene_text(seed, None))
    run = [sys.executable, "-m", "ftsensord"]
    subprocess.run(
        [
            *run,
            "dataset",
            "-o",
            str(folder / "ds.json"),
            "--scene",
            str(folder / "scene.toml"),
            "--seed",
            str(seed),
        ],
        check=True,
        capture_output=True,
    )
    subprocess.run(
        [*run, "calibrate", str(folder / "ds.json"), "-o", str(folder / "cal.json"), "--linear-only"],
        check=True,
        capture_output=True,
    )
    return folder / "cal.json"


def config_text(cal: Path) -> str:
    return f"""
version = 1
bus = "sim:scene.toml"
rate_hz = 100
scheduler = "overlapped"
temperature_every = 0
[[sensor]]
name = "sensor1"
addresses = [0x0C, 0x0D, 0x0E, 0x0F, 0x10, 0x11, 0x12, 0x13]
calibration = "{cal}"
"""


def run_part(seed: int, loads: np.ndarray, samples: int) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(case, errors, sigmas) of each load on part ``seed``: samples x 6 each."""
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        cal = calibrate(folder, seed)
        (folder / "ftsensord.toml").write_text(config_text(cal))
        (folder / "scene.toml").write_text(scene_text(seed, None))
        config = load_config(folder / "ftsensord.toml")
        scene = load_scene(folder / "scene.toml")
        rig = InProcess(config, scene, subscribe=b"", seed=seed)
        try:
            p = rig.daemon.sensors[0]
            for _ in range(120):
                step(rig)
            flux = []
            for _ in range(100):
                step(rig)
                flux.append(p.last_flux.copy())
            zero = np.mean(flux, axis=0)
            p.tare(zero, None, len(flux))
            for k, load in enumerate(loads):
                rig.scene.set_load(0, StaticLoad(np.asarray(load, dtype=float)))
                for _ in range(20):  # the filter and the silicone, if any, settle
                    step(rig)
                got = [step(rig) for _ in range(samples)]
                w = np.array([g[0] for g in got])
                s = np.array([g[1] for g in got])
                out.append(("rest" if k == 0 else "held", w - load, s))
        finally:
            rig.close()
    return out


def step(rig: InProcess) -> tuple[np.ndarray, np.ndarray]:
    """One cycle; sensor1's wrench and sigma as published."""
    deadline = rig.clock.now() + rig.daemon.period_s
    rig.daemon.cycle()
    rig.clock.wait_until(deadline)
    w = s = np.full(6, np.nan)
    while rig.sub.poll(0):
        x = wire.decode(rig.sub.recv())
        if x.topic == "wrench/sensor1":
            w = x.values
        elif x.topic == "sigma/wrench/sensor1":
            s = x.values
    return w, s


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", type=int, nargs="+", default=[71, 72, 73])
    parser.add_argument("--loads", type=int, default=8)
    parser.add_argument("--samples", type=int, default=300)
    args = parser.parse_args(argv)
    rng = np.random.default_rng(7100)
    rows: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {"rest": [], "held": []}
    for seed in args.parts:
        loads = [np.zeros(6)] + [
            rng.uniform(-1, 1, 6) * np.array([2.0, 2.0, 2.0, 0.04, 0.04, 0.04]) for _ in range(args.loads)
        ]
        for case, err, sig in run_part(seed, np.array(loads), args.samples):
            rows[case].append((err, sig))
    print(
        f"parts (tolerance seeds) {args.parts}; {args.samples} samples a load; linear estimator, packaged settings"
    )
    print("| case | samples | within | " + " | ".join(AXES) + " | median sigma |")
    print("|---|---|---|" + "---|" * 6 + "---|")
    for case, parts in rows.items():
        if not parts:
            continue
        err = np.concatenate([e for e, _ in parts])
        sig = np.concatenate([s for _, s in parts])
        ok = np.all(np.isfinite(sig), axis=1) & np.all(np.isfinite(err), axis=1)
        err, sig = err[ok], sig[ok]
        for k in (1, 2):
            inside = np.mean(np.abs(err) <= k * sig, axis=0) * 100
            med = np.median(sig, axis=0)
            print(
                f"| {case} | {len(err)} | {k} sigma | "
                + " | ".join(f"{v:.0f} %" for v in inside)
                + " | "
                + (", ".join(f"{v:.3g}" for v in med) if k == 1 else "")
                + " |"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
