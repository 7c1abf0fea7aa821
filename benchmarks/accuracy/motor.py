"""Motors nearby: a motor's point dipole a few cm from the tool, through the
daemon, on as-built parts the project does not otherwise use. Writes docs/results/motor-figures.md.

    python -m benchmarks.accuracy.motor            # the figures in docs/ (2 processes)
    python -m benchmarks.accuracy.motor --quick    # structure only (tests/test_motor_bench.py)

Per part (seeds 11, 12, 13; the default scene's tolerances and the Earth's field): the
paper's calibration run on the simulated bus and both fits, as `ftsensord dataset` and
`calibrate` do (`simulate_dataset`, `calibrate`), written to a calibration file. Then the
daemon (overlapped, 100 Hz, virtual clock, one sensor, the linear or the nonlinear
estimator; `stray_field` "uniform", "gradient" and "world", the last with the scene's
orientation sent to the daemon's orientation stream every cycle, as a haptic application
sends its kinematics) reads the part in a scene with one
`[[stray_source]]`: 2 A m^2, 15 cm from the sensor's centre (and 25 cm for "on after
tare"), fixed in the world, its direction and its moment's drawn from the part's seed. The tool is tared
(100 samples, the daemon's
own tare) at its first orientation, then turned through the accuracy sweep's orientations
(benchmarks/accuracy/accuracy.py's `SWEEP`), each held `--hold` s, 0.2 s between. Scenarios:

- "on after tare": the motor off at the tare, switched on before the first hold; no load;
- "tared on": the motor on throughout, tared with it on; no load;
- "100 g, tared on": as "tared on", with the paper's 100 g validation loads (its
  validation poses: load and orientation together) instead of no load.

Per hold: the median of its unflagged samples (any value flag but `late` counts; the
first 50 ms of the hold are left out as the turn's end), against the truth (zero, or the
pose's wrench). Reported: the RMS over holds of those medians per axis, the largest,
the holds with no unflagged sample, and the samples flagged.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import uuid
from concurrent.futures import ProcessPoolExecutor
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zmq

from benchmarks.common import PAPER, RESULTS, SENSOR1, SWEEP, daemon_config, part_table
from ftsensord.calibration.fit import rmse, singular_values_ka
from ftsensord.calibration.procedure import calibrate, simulate_dataset
from ftsensord.config.file import load_config
from ftsensord.config.sensors import STRAY_FIELDS
from ftsensord.model import se3
from ftsensord.protocol import orientation, wire
from ftsensord.sim import load_scene
from ftsensord.sim.loads import paper_plan
from ftsensord.testing.harness import InProcess

SEEDS = (11, 12, 13)
MOMENT_AM2 = 2.0
#: The turn between two holds (s); and what of a hold's start is left out (s): the turn
#: has ended, and a sample's conversions all fall in the hold.
MOVE_S, SETTLE_S = 0.2, 0.05
#: The tare: asked at TARE_AT_S, 100 samples (the daemon's default, 1 s at 100 Hz); the
#: motor is switched on at ON_S, after it, and the first hold starts at START_S. A tare
#: takes unflagged samples only: with the motor on, the tool held still there 3.6 s gives it
#: 360 cycles to find them (a tare answered after the first turn began is reported late).
TARE_AT_S, TARE_SAMPLES, ON_S, START_S = 0.2, 100, 3.65, 4.0
SCENARIOS = ("on after tare", "tared on", "100 g, tared on")
TARGET = np.array([0.05, 0.05, 0.05, 2e-3, 2e-3, 2e-3])  # the aim at rest near a motor, N and Nm


def placement(seed: int, distance_m: float) -> tuple[np.ndarray, np.ndarray]:
    """The motor's position (m) and moment (A m^2) in the world for part ``seed``."""
    rng = np.random.default_rng(1000 + seed)
    d, m = rng.normal(size=3), rng.normal(size=3)
    return d / np.linalg.norm(d) * distance_m, m / np.linalg.norm(m) * MOMENT_AM2


def calibrate_part(seed: int, folder: Path, args: argparse.Namespace) -> tuple[Path, list[str]]:
    """`ftsensord dataset` and `calibrate` of part ``seed``: the calibration file, and the
    price of each `STRAY_FIELDS` model as lines: sigma_max(K A) and isotropy (forces,
    torques), and the linear 100 g validation RMSE against Table II."""
    scene = folder / f"part{seed}.toml"
    scene.write_text(part_table(seed))
    ds = simulate_dataset(
        scene,
        "sensor1",
        "six-axis",
        poses=args.fit_poses,
        validation_poses=args.loads,
        samples=args.samples,
        seed=seed,
    )
    cal, _ = calibrate(ds, serial=f"part{seed}", frame="sensor1", allow_poor_fit=args.quick)
    path = folder / f"part{seed}.json"
    cal.save(path)
    validation = ds.select(ds.split == "validation")
    price = []
    for stray, model in (("uniform", cal.model), ("gradient", cal.model.with_gradient())):
        sv, err = singular_values_ka(model), rmse(model, validation)
        price.append(
            f"| {seed} | {stray} | {sv['forces'][0]:.4g} | {sv['forces'][-1] / sv['forces'][0]:.3f} "
            f"| {sv['torques'][0]:.4g} | {sv['torques'][-1] / sv['torques'][0]:.3f} | {cells(err)} "
            f"| {np.max(err / PAPER):.3f} |"
        )
    return path, price


@dataclass
class Run:
    errors: np.ndarray  # (holds, 6) median of each hold's unflagged samples minus the truth; NaN: none
    flagged: int
    samples: int
    tare: str  # "ok" or the daemon's refusal


def run(
    seed: int,
    cal: Path,
    estimator: str,
    stray: str,
    scenario: str,
    distance_m: float,
    folder: Path,
    args: argparse.Namespace,
) -> Run:
    """One scenario through the daemon (module docstring)."""
    if scenario.startswith("100 g"):
        poses = [p for p, split in paper_plan(n_fit=1, n_validation=args.loads) if split == "validation"]
        holds = [(p.orientation(), p.wrench()) for p in poses]
    else:
        holds = [(R, np.zeros(6)) for R in SWEEP[: args.orientations]]
    first = SWEEP[0] if not scenario.startswith("100 g") else holds[0][0]
    # Rows: still until the first turn, then per hold its start and end (a turn between).
    t = START_S - MOVE_S
    times, rotations, loads = [0.0, t], [first, first], [np.zeros(6), np.zeros(6)]
    starts = []
    for R, w in holds:
        times += [t + MOVE_S, t + MOVE_S + args.hold]
        rotations += [R, R]
        loads += [w, w]
        starts.append(t + MOVE_S)
        t += MOVE_S + args.hold
    position, moment = placement(seed, distance_m)
    on = scenario == "on after tare"
    scene = (
        part_table(seed)
        + '[sensor.orientation]\nkind = "recorded"\n'
        + f"times_s = {times}\nrotvec_deg = {[np.degrees(se3.log_so3(R)).tolist() for R in rotations]}\n"
        + '[sensor.load]\nkind = "recorded"\n'
        + f"times_s = {times}\nwrenches = {[w.tolist() for w in loads]}\n"
        + f"[[stray_source]]\nposition_m = {position.tolist()}\nmoment_am2 = {moment.tolist()}\n"
        + (f"times_s = [{ON_S}, {ON_S + 0.01}]\nscale = [0.0, 1.0]\n" if on else "")
    )
    (folder / "scene.toml").write_text(scene)
    (folder / "ftsensord.toml").write_text(
        daemon_config()
        + f"""[[sensor]]
name = "sensor1"
addresses = [{SENSOR1}]
calibration = "{cal}"
estimator = "{estimator}"
stray_field = "{stray}"
"""
        + (
            ""
            if stray != "world"
            else """[gravity]
orientation = "stream"
[gravity.sensor1]
mass_kg = 0.0
com_m = [0.0, 0.0, 0.0]
"""
        )
    )
    # "world" learns from the tool's orientation, which a haptic application sends every tick:
    # here the scene's own, each cycle, over an inproc pair.
    # A fresh name each run: ZeroMQ frees a closed socket's inproc name later, in its own thread,
    # and the previous run's (same seed, estimator and folder) was once still taken on a loaded host.
    ctx, name = zmq.Context.instance(), f"inproc://orientation-{uuid.uuid4().hex}"
    ori_sub, ori_pub = ctx.socket(zmq.SUB), ctx.socket(zmq.PUB)
    ori_sub.setsockopt(zmq.SUBSCRIBE, b"")
    ori_sub.bind(name)
    ori_pub.connect(name)
    scene_obj = load_scene(folder / "scene.toml")
    rig = InProcess(
        load_config(folder / "ftsensord.toml"),
        scene_obj,
        subscribe=b"wrench/",
        seed=seed,
        **({"orientation": ori_sub} if stray == "world" else {}),
    )
    sensor = scene_obj.sensors[0]
    samples: list[wire.Sample] = []
    reply, replied_s = None, 0.0
    try:
        for k in range(int(round(t * 100))):
            if k == int(TARE_AT_S * 100):
                rig.req.send(
                    json.dumps({"cmd": "tare", "sensor": "sensor1", "samples": TARE_SAMPLES}).encode()
                )
            deadline = rig.clock.now() + rig.daemon.period_s
            if stray == "world":
                now = rig.clock.now()
                ori_pub.send(orientation.encode("sensor1", sensor.orientation.rotation(now), now))
            rig.daemon.cycle()
            rig.daemon.handle_control()
            rig.clock.wait_until(deadline)
            while rig.sub.poll(0):
                samples.append(wire.decode(rig.sub.recv()))
            if reply is None and k > int(TARE_AT_S * 100) and rig.req.poll(0):
                reply, replied_s = json.loads(rig.req.recv()), rig.clock.now()
    finally:
        rig.close()
        ori_sub.close(linger=0)
        ori_pub.close(linger=0)
    errors, flagged, used = [], 0, 0
    samples = [s for s in samples if s.topic == "wrench/sensor1"]  # not "world"'s compensated stream
    for start, (_, truth) in zip(starts, holds, strict=True):
        hold = [s for s in samples if start + SETTLE_S <= s.t_mono < start + args.hold]
        good = [s.values for s in hold if not s.flags & ~wire.FLAG_LATE]
        flagged += len(hold) - len(good)
        used += len(hold)
        errors.append(np.median(good, axis=0) - truth if good else np.full(6, np.nan))
    tare = "ok" if reply and reply.get("ok") else f"refused: {reply}"
    if reply is not None and replied_s > START_S - MOVE_S:
        tare += f", late ({replied_s:.2f} s)"
    return Run(np.array(errors), flagged, used, tare)


def rows_of(seed: int, cal: Path, estimator: str, folder: Path, args: argparse.Namespace) -> list[str]:
    """Every scenario of part ``seed`` with ``estimator``, both `STRAY_FIELDS`: table rows."""
    rows = []
    folder = folder / f"{seed}-{estimator}"  # the daemon's files, one folder per worker
    folder.mkdir()
    for stray in STRAY_FIELDS:
        for scenario in SCENARIOS:
            for distance in (0.15, 0.25) if scenario == "on after tare" else (0.15,):
                r = run(seed, cal, estimator, stray, scenario, distance, folder, args)
                worst = (
                    np.nanmax(np.abs(r.errors), axis=0)
                    if not np.isnan(r.errors).all()
                    else np.full(6, np.nan)
                )
                rows.append(
                    f"| {seed} | {estimator}, {stray} | {scenario} | {distance * 100:g} cm "
                    f"| {cells(rms(r.errors))} | {np.max(worst[:3]):.3g} N, {np.max(worst[3:]) * 1e3:.3g} mNm "
                    f"| {int(np.isnan(r.errors).any(axis=1).sum())} of {len(r.errors)} "
                    f"| {r.flagged} of {r.samples} | {r.tare} |"
                )
                print(rows[-1], flush=True)
    return rows


def rms(errors: np.ndarray) -> np.ndarray:
    """RMS over the holds that have an unflagged sample (N, Nm per axis)."""
    kept = errors[~np.isnan(errors).any(axis=1)]
    return np.sqrt(np.mean(kept**2, axis=0)) if len(kept) else np.full(6, np.nan)


def cells(v: np.ndarray) -> str:
    return " | ".join(f"{x:.3g}" for x in v * np.array([1, 1, 1, 1e3, 1e3, 1e3]))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="one part, a small calibration, few holds (seconds)")
    ap.add_argument("--jobs", type=int, default=2, help="processes (default 2; the quick mode 1)")
    ap.add_argument("--out", type=Path, default=RESULTS / "motor-figures.md")
    args = ap.parse_args(argv)
    args.seeds = SEEDS[:1] if args.quick else SEEDS
    args.jobs = 1 if args.quick else args.jobs
    args.fit_poses, args.samples = (40, 10) if args.quick else (193, 100)
    args.loads, args.orientations, args.hold = (4, 4, 0.3) if args.quick else (48, 48, 1.0)
    args.estimators = ("linear",) if args.quick else ("linear", "nonlinear")
    lines = [
        "# Motors nearby: figures",
        "",
        f"`python -m benchmarks.accuracy.motor{' --quick' if args.quick else ''}` (written by it). Parts: seeds "
        f"{', '.join(map(str, args.seeds))} (the default scene's tolerances, the Earth's field); calibration "
        f"{args.fit_poses} fit poses, 24 no-load, {args.loads} validation (100 g), {args.samples} readings a "
        f"pose. A {MOMENT_AM2:g} A m^2 dipole fixed in the world; {args.orientations} orientations (or "
        f"{args.loads} validation poses), each held {args.hold:g} s (about "
        f"{int(round((args.hold - SETTLE_S) * 100))} samples), 100 Hz. Per hold the median of its unflagged "
        "samples minus the truth; RMS over the holds (N x3, mNm x3), the largest over the holds (max |.| "
        "on any axis: N, mNm), holds without an "
        "unflagged sample, samples flagged.",
        "",
    ]
    lines += [
        "| part | estimator, stray_field | scenario | distance | Fx | Fy | Fz | Mx | My | Mz | largest F, M "
        "| holds all flagged | samples flagged | tare |",
        "|---" * 14 + "|",
    ]
    parts = [
        "",
        "The price, without a motor: sigma_max(K A) (N/uT, Nm/uT) and isotropy, and the linear "
        f"100 g validation ({args.loads} poses of the calibration run, {args.samples} readings each; N x3, "
        "mNm x3) with its largest ratio to Table II:",
        "",
        "| part | stray_field | sigma_max F | isotropy F | sigma_max M | isotropy M | Fx | Fy | Fz | Mx | My "
        "| Mz | / Table II |",
        "|---" * 13 + "|",
    ]
    # One process in the quick mode: no fork of a test process that holds ZeroMQ sockets.
    with (
        tempfile.TemporaryDirectory() as tmp,
        ProcessPoolExecutor(args.jobs) if args.jobs > 1 else nullcontext() as pool,
    ):
        folder = Path(tmp)
        mapper = map if pool is None else pool.map
        calibrated = list(
            mapper(calibrate_part, args.seeds, [folder] * len(args.seeds), [args] * len(args.seeds))
        )
        for _, price in calibrated:
            parts += price
        tasks = [
            (seed, cal, estimator)
            for seed, (cal, _) in zip(args.seeds, calibrated, strict=True)
            for estimator in args.estimators
        ]
        for rows in mapper(rows_of, *zip(*tasks, strict=True), [folder] * len(tasks), [args] * len(tasks)):
            lines += rows
    lines += parts + [
        "",
        f"Aim: RMS within {TARGET[0]} N and {TARGET[3] * 1e3:g} mNm; at 25 cm nothing flagged.",
    ]
    args.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
