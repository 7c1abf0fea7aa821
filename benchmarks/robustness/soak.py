"""Soak: the daemon at 100 Hz with 16 simulated chips under random faults, watched from outside.

Writes a scene whose `[[fault]]` list is a random schedule (every kind but "slow": a bus
slower than the rate needs is refused by design, see docs/design/reliability.md), runs
`ftsensord run` on it with real 400 kHz wire time, subscribes to every wrench stream, and
reports: faults injected; samples flagged; sequence gaps and the longest silence a
subscriber saw; each silence over 1.5 periods and each skipped deadline, with the fault
active then; recovery time after each fault that had no other fault near it (fault end to
the first unflagged sample of its sensor); missed and late cycles while it watched; memory
at start, each minute and at the end; whether the daemon was still running; and unflagged
wrong samples: every sample of every wrench stream with no flag but `late` is compared with
the truth, the stream's mean over the unflagged samples of fault-free stretches (no fault
from 50 ms before its start to 1 s after its end: the wrench the daemon's own estimate gives
the applied static load, whose bias against that load, the model's, is reported beside), in
sigmas of one sample's noise per axis, the spread (standard deviation) of the same samples
(benchmarks/accuracy/faults_truth.py's criterion and code). A sample beyond 5 sigma on any axis is then
told apart by its chips (the flux streams, the same way): made by the noise when every chip
read within 5 of its own sigmas of its fault-free mean, wrong when one did not (the target:
0). Beside them, what noise alone makes: a Gaussian's count and the chips' noise as it is,
rounded to the LSB (benchmarks/accuracy/noise_tails.py). The noise the calibration's K A and the chip
settings predict (as the daemon's consistency check takes it, `channel_sigma_t`) is reported
as a cross-check. ``--save FILE.npz`` keeps every sample and the faults for a later look.
Run:

    python -m benchmarks.robustness.soak --minutes 30 [--scheduler overlapped] [--fifo 50] [--save \
        F.npz]  # the docs' figures
    python -m benchmarks.robustness.soak --minutes 0.3       # quick mode (CI runs it as a test)
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np

from benchmarks.common import WRONG_SIGMA, tail_rate, unflagged_error_sigma, wrench_noise
from ftsensord.client import ControlClient, Subscriber
from ftsensord.config.file import Config, load_config
from ftsensord.model import se3
from ftsensord.processing.pipeline import channel_sigma_t
from ftsensord.protocol import wire
from ftsensord.sim import load_scene
from ftsensord.sim.chip import FieldSource
from ftsensord.sim.faults import random_faults
from ftsensord.sim.scene import default_scene_text
from ftsensord.testing.harness import packaged_config, start_daemon, stop

SENSORS = {"sensor1": range(0x0C, 0x14), "sensor2": range(0x14, 0x1C)}
RATE_HZ = 100.0  # the packaged configuration's rate
LOAD = [1.0, -0.5, 0.8, 0.02, -0.01, 0.015]


def scene_text(faults) -> str:
    # The default scene (the room and the part the packaged calibrations were fitted on).
    lines = [default_scene_text(LOAD)]
    for f in faults:
        lines += ["[[fault]]", f'kind = "{f.kind}"', f"at_s = {f.at_s:.4f}", f"until_s = {f.until_s:.4f}"]
        if f.address is not None:
            lines.append(f"address = {f.address}")
        if f.kind == "drift_register":
            lines += [f"register = {f.register}", f"value = {f.value}"]
        if f.kind == "saturate":
            lines.append(f"field_mt = {f.field_mt}")
    return "\n".join(lines) + "\n"


def rss_kib(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


def applied(config: Config) -> dict[str, np.ndarray]:
    """The static load each wrench stream should show (N, Nm): LOAD on sensor1, none on
    sensor2, and at the tip LOAD moved from sensor1's pose (as processing.pipeline.tip_wrench)."""
    tip = se3.wrench_transform(config.tool_poses["sensor1"]) @ np.array(LOAD)
    return {"wrench/sensor1": np.array(LOAD), "wrench/sensor2": np.zeros(6), "wrench/tip": tip}


def model_sigma(config: Config) -> dict[str, np.ndarray]:
    """One sample's noise per axis (N, Nm) that the calibrations' K A and the chip settings'
    channel noise predict, with all chips (the tip: both sensors' moved and added, independent)."""
    cov = {}
    for s in config.sensors:
        KA = s.calibration.model.KA
        cov[s.name] = KA @ np.diag(channel_sigma_t(config.settings, len(s.addresses)) ** 2) @ KA.T
    out = {f"wrench/{n}": np.sqrt(np.diag(c)) for n, c in cov.items()}
    if config.tool_poses:
        moved = [se3.wrench_transform(T) for T in config.tool_poses.values()]
        out["wrench/tip"] = np.sqrt(np.diag(sum(X @ cov[n] @ X.T for X, n in zip(moved, config.tool_poses))))
    return out


#: A chip's reading further than this from its fault-free mean, in its own spread, is not
#: noise: 2 LSB at the paper's RES 3 (an LSB is 2.3 of that spread), reached by noise about
#: once in 10,000 readings, while every fault moves a reading by many LSB or flags it.
CHIP_NOISE_SIGMA = 5.0
#: Samples a stream drawn for the noise-alone expectation (benchmarks/accuracy/noise_tails.py): enough
#: for about 5 events at sensor2's 12 per million, a few seconds.
TAIL_SAMPLES = 400_000


def wrong_samples(
    samples: dict[str, list],
    values: dict[str, list],
    faults: list,
    config: Config,
    scene: FieldSource,
    tail_samples: int = TAIL_SAMPLES,
) -> dict:
    """Unflagged samples more than WRONG_SIGMA from the truth, per stream (see the module's
    doc), each told apart by its chips: made by noise (every chip of the stream within
    CHIP_NOISE_SIGMA of its fault-free reading) or wrong (a chip beyond, or its flux missing)."""
    truth_load, predicted = applied(config), model_sigma(config)
    noise_alone = wrench_noise(config, scene, tail_samples)

    def quiet_and_clean(topic: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Times, samples with no flag but `late`, and those of them in fault-free stretches."""
        t = np.array([r[1] for r in samples[topic]])
        clean = np.array([r[2] & ~wire.FLAG_LATE == 0 for r in samples[topic]], dtype=bool)
        quiet = np.ones(len(t), dtype=bool)
        for f in faults:  # the same window as fault_near: from 50 ms before to 1 s after
            quiet &= (t < f.at_s - 0.05) | (t > f.until_s + 1.0)
        return t, clean, clean & quiet

    chips_off: dict[str, dict[int, np.ndarray]] = {}  # per sensor: seq -> each chip beyond its noise
    for name in SENSORS:
        topic = f"flux/{name}"
        _, _, ok = quiet_and_clean(topic)
        flux = np.array(values[topic])
        # A NaN (a chip not read) counts as beyond: nothing says it was right.
        off = ~(np.abs(flux - flux[ok].mean(axis=0)) / flux[ok].std(axis=0) <= CHIP_NOISE_SIGMA)
        chips_off[name] = {
            r[0]: np.flatnonzero(o.reshape(-1, 3).any(axis=1)) for r, o in zip(samples[topic], off)
        }

    out: dict = {"per_stream": {}, "wrong": []}
    for topic, rows in samples.items():
        if not topic.startswith("wrench/") or not rows:
            continue
        t, clean, quiet = quiet_and_clean(topic)
        v = np.array(values[topic])
        ref_rows = v[quiet]
        # The mean, not the median: at RES 3 a reading takes few levels and the median of
        # their sum sits up to 0.15 sigma off the mean that the noise spreads around.
        reference = ref_rows.mean(axis=0)
        sigma = ref_rows.std(axis=0)
        err = unflagged_error_sigma(v, reference, sigma, clean)
        beyond = np.flatnonzero(err > WRONG_SIGMA)
        sensors = [topic.split("/")[1]] if topic.split("/")[1] in SENSORS else list(SENSORS)
        by_chip = {
            i: [f"{n}/chip{c}" for n in sensors for c in chips_off[n].get(rows[i][0], [-1])] for i in beyond
        }
        bad = [i for i in beyond if by_chip[i]]  # a chip beyond its noise, or no flux to tell (chip -1)
        # The same comparison on the flagged samples with a value: wrong ones the flags kept
        # from the user (under a static load few: the chips left mostly give the right wrench).
        flagged = ~clean & ~np.isnan(v).any(axis=1)
        caught = int(np.sum(unflagged_error_sigma(v, reference, sigma, flagged) > WRONG_SIGMA))
        out["per_stream"][topic] = {
            "judged_unflagged": int(clean.sum()),
            "reference_from": len(ref_rows),
            "reference": reference.round(5).tolist(),
            "bias_vs_applied": (reference - truth_load[topic]).round(5).tolist(),
            "sigma_measured": sigma.round(6).tolist(),
            "sigma_predicted": predicted[topic].round(6).tolist() if topic in predicted else None,
            "unflagged_beyond_5_sigma": len(beyond),
            "made_by_noise": len(beyond) - len(bad),
            "unflagged_wrong": len(bad),
            "flagged_beyond_5_sigma": caught,
            "worst_unflagged_sigma": round(float(err.max(initial=0.0)), 2),
            "worst_at_s": round(float(t[np.argmax(err)]), 3) if len(err) else None,
            # Under Gaussian noise alone, over WRONG_SIGMA on one axis has odds erfc(5 / sqrt 2) = 5.7e-7.
            "expected_by_gaussian_noise": round(
                float(clean.sum()) * 6 * math.erfc(WRONG_SIGMA / math.sqrt(2)), 3
            ),
            # The chips' noise as it is: Gaussian, then rounded to the LSB (noise_tails.py).
            "expected_by_chip_noise": round(
                float(clean.sum()) * tail_rate(noise_alone[topic], WRONG_SIGMA), 3
            ),
        }
        for i in beyond[: 100 - len(out["wrong"])]:  # a regression would list thousands: the first 100 tell
            active = [
                f"{f.kind}@{f.address:#x}" if f.address is not None else f.kind
                for f in faults
                if f.at_s - 0.5 <= t[i] <= f.until_s + 2.0
            ]
            axis = int(np.argmax(np.abs(v[i] - reference) / sigma))
            off = abs(v[i, axis] - reference[axis])  # the same error in the predicted sigma, for comparison
            out["wrong"].append(
                {
                    "stream": topic,
                    "t_s": round(float(t[i]), 3),
                    "seq": rows[i][0],
                    "sigma": round(float(err[i]), 2),
                    "axis": ["Fx", "Fy", "Fz", "Mx", "My", "Mz"][axis],
                    "predicted_sigmas": round(float(off / predicted[topic][axis]), 2)
                    if topic in predicted
                    else None,
                    "chips_beyond_noise": by_chip[i] or ["none: made by noise"],
                    "flags": wire.flag_names(rows[i][2]),
                    "faults_around": active or ["none"],
                }
            )
    for key in ("unflagged_beyond_5_sigma", "made_by_noise", "unflagged_wrong"):
        out[key] = sum(s[key] for s in out["per_stream"].values())
    out["worst_unflagged_sigma"] = max(
        (s["worst_unflagged_sigma"] for s in out["per_stream"].values()), default=0.0
    )
    return out


def soak(
    minutes: float,
    seed: int = 1,
    per_minute: float = 6.0,
    scheduler: str = "burst",
    fifo: int = 0,
    save: Path | None = None,
) -> dict:
    """``fifo``: run the daemon SCHED_FIFO at this priority, as the systemd unit does (0: not);
    ``save``: an .npz file to keep every sample in (wrench and flux streams, and the faults)."""
    duration = minutes * 60
    rng = np.random.default_rng(seed)
    faults = [
        f
        for f in random_faults(list(range(0x0C, 0x1C)), duration, rng, per_minute=per_minute)
        if f.kind != "slow"
    ]
    with tempfile.TemporaryDirectory() as tmp:
        tmp_path = Path(tmp)
        (tmp_path / "scene.toml").write_text(scene_text(faults))
        scene = load_scene(tmp_path / "scene.toml")  # the truth of the noise-alone expectation
        config = packaged_config(
            tmp_path / "ftsensord.toml", bus='"sim:scene.toml"', scheduler=f'"{scheduler}"'
        )
        parsed = load_config(config)
        proc, notify = start_daemon(config, tmp_path, fifo=fifo)
        folder = tmp_path / "ftsensord"
        control = ControlClient(f"ipc://{folder / 'control'}", timeout_s=5)
        status0 = control.status()
        t0_daemon = time.monotonic() - status0["uptime_s"]  # the scene's clock starts with the daemon
        topics = [f"wrench/{n}" for n in SENSORS] + ["wrench/tip"]
        # The flux streams too: an outlier's chips tell noise from a fault.
        topics += [f"flux/{n}" for n in SENSORS]
        samples: dict[str, list[tuple[int, float, int]]] = {t: [] for t in topics}
        values: dict[str, list[np.ndarray]] = {t: [] for t in topics}
        rss = [rss_kib(proc.pid)]  # at start, then every minute: growth shows as a trend
        with Subscriber(f"ipc://{folder / 'wrench'}", topics) as sub:
            end = time.monotonic() + duration
            next_rss = time.monotonic() + 60
            while time.monotonic() < end and proc.poll() is None:
                s = sub.receive(timeout_s=2)
                if s is not None:
                    samples[s.topic].append((s.seq, s.t_mono - t0_daemon, s.flags))
                    values[s.topic].append(s.values)
                if time.monotonic() >= next_rss:
                    rss.append(rss_kib(proc.pid))
                    next_rss += 60
            gaps = dict(sub.gaps)
        alive = proc.poll() is None
        rss_end = rss_kib(proc.pid) if alive else 0
        status1 = control.status() if alive else {}
        exit_code = stop(proc, notify)
    if save:
        np.savez_compressed(
            save,
            fault_kind=np.array([f.kind for f in faults]),
            fault_at_s=np.array([f.at_s for f in faults]),
            fault_until_s=np.array([f.until_s for f in faults]),
            fault_address=np.array([-1 if f.address is None else f.address for f in faults]),
            **{
                f"{t}:{k}": np.array([r[i] for r in samples[t]])
                for t in topics
                for i, k in enumerate(("seq", "t_s", "flags"))
            },
            **{f"{t}:values": np.array(values[t]) for t in topics},
        )
    wrong = wrong_samples(samples, values, faults, parsed, scene)
    samples = {t: v for t, v in samples.items() if t.startswith("wrench/")}
    flagged = {t: sum(1 for _, _, f in v if f) for t, v in samples.items()}
    silences = {t: max(np.diff([x[1] for x in v]), default=0.0) for t, v in samples.items()}
    # Recovery after faults with no other fault within 2 s either side of them.
    recoveries = []
    for f in faults:
        if f.kind == "drift_register":
            continue  # a drift has no end: it is found and repaired, not cleared
        if any(g is not f and g.at_s < f.until_s + 2 and g.until_s > f.at_s - 2 for g in faults):
            continue
        names = [n for n, a in SENSORS.items() if f.address in a] if f.address is not None else list(SENSORS)
        for name in names:
            after = [(t, fl) for _, t, fl in samples[f"wrench/{name}"] if t >= f.until_s]
            clean = next((t for t, fl in after if not fl & ~wire.FLAG_LATE), None)
            if clean is not None:
                recoveries.append(clean - f.until_s)

    def fault_near(t: float) -> str:
        """The kind of fault active at t (to 1 s after it), or "no fault"."""
        return next((f.kind for f in faults if f.at_s - 0.05 <= t <= f.until_s + 1.0), "no fault")

    s1 = samples["wrench/sensor1"]
    near = [fault_near(t) for _, t, _ in s1]
    late_by_kind = Counter(near[i] for i, (_, _, fl) in enumerate(s1) if fl & wire.FLAG_LATE)
    times = np.array([x[1] for x in s1])
    # A silence over 1.5 periods is a cycle at least half a period late (1.5 tells it from jitter).
    long = np.flatnonzero(np.diff(times) > 1.5 / RATE_HZ)
    silences_over = [(float(times[i]), float(times[i + 1] - times[i]), near[i]) for i in long]
    # The loop keeps a fixed grid of deadlines and skips one when it has fallen a whole period
    # behind, which can happen by small overruns with no silence: a skip shows as the samples'
    # times running one period ahead of their count. Lateness stays under a period, so the
    # floor of that lead counts skips; its running maximum ignores read jitter (+-0.05 period).
    lead = np.maximum.accumulate(np.floor((times - times[0]) * RATE_HZ - np.arange(len(times)) + 0.05))
    skips = [(float(times[i]), near[i]) for i in np.flatnonzero(np.diff(lead) > 0) + 1]
    worst = int(np.argmax(np.diff(times))) if len(s1) > 1 else 0
    t_silence = s1[worst][1] if s1 else 0.0
    return {
        "minutes": minutes,
        "scheduler": scheduler,
        "daemon_fifo": fifo,
        "faults_injected": len([f for f in faults if f.at_s < duration]),
        "fault_kinds": sorted({f.kind for f in faults}),
        "samples": {t: len(v) for t, v in samples.items()},
        "flagged": flagged,
        "sequence_gaps": gaps,
        "longest_silence_s": silences,
        "longest_silence_at_s": t_silence,
        "longest_silence_during": [f.kind for f in faults if f.at_s - 0.05 <= t_silence <= f.until_s + 1.0],
        "late_samples_by_fault_kind": dict(late_by_kind),
        "silences_over_1_5_periods": silences_over,
        "skipped_deadlines_seen": skips,
        "share_of_time_near_a_fault": 1 - near.count("no fault") / max(len(near), 1),
        "recoveries": len(recoveries),
        "recovery_max_s": max(recoveries, default=None),
        "recovery_median_s": float(np.median(recoveries)) if recoveries else None,
        # Counted from when the soak connected: start-up is not what it judges.
        **{k: status1[k] - status0[k] for k in ("cycles", "missed_cycles", "late_cycles") if k in status1},
        "missed_cycles_before_watch": status0["missed_cycles"],
        "rss_kib_start": rss[0],
        "rss_kib_end": rss_end,
        "rss_kib_each_minute": rss[1:],
        "alive_at_end": alive,
        "exit_code": exit_code,
        "wrong_samples": wrong,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=30.0)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--per-minute", type=float, default=6.0, help="faults per minute on average")
    parser.add_argument("--scheduler", choices=("overlapped", "burst"), default="burst")
    parser.add_argument(
        "--fifo",
        type=int,
        default=0,
        help="run the daemon SCHED_FIFO at this priority (0: not; the unit: 50)",
    )
    parser.add_argument(
        "--save",
        type=Path,
        default=None,
        help="keep every sample (wrench and flux streams) and the faults in this .npz",
    )
    args = parser.parse_args()
    report = soak(args.minutes, args.seed, args.per_minute, args.scheduler, args.fifo, args.save)
    print(json.dumps(report, indent=1))
    return 0 if report["alive_at_end"] and report["exit_code"] == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
