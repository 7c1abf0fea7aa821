"""The trade, dynamic: moving loads at the chip settings and schedulers of docs/results/tradeoff.md on a
part whose silicone relaxes; writes docs/results/tradeoff-dynamic.md and docs/results/tradeoff-dynamic.png.

The part and its calibration are benchmarks/accuracy/creep.py's (`creep.calibrated_part`: the default
scene's sensor1 with the default series, calibrated by `ftsensord dataset` and `ftsensord
calibrate` at their defaults, the step-and-hold among them). For each chip setting (OSR, DIG_FILT) of
docs/results/tradeoff.md and each scheduler (naive, overlapped, burst), the daemon runs in process on a
virtual clock at that scheduler's computed bound for the setting (the simulated bus spends the wire's time, so the
virtual loop reaches it) and publishes sensor1's wrench under one profile: rest, 2 N sines
on Fx at 0.5, 1, 2 and 5 Hz, a 2 N step on Fx held 30 s, then the training-like profile.

Without the compensation: as published (the stage passing everything through). With it: the
daemon's stage (`CreepCompensation`) over those samples in order, each with its flags (a
flagged one kept out of the state, as in the daemon); with averaging 1 and no low-pass (these
runs) nothing else acts on the wrench after the stage, and the result is checked against the
daemon's own compensated run at one loop (equal to 1e-9 N). One run a loop instead of two.

Figures against the scene's truth: the held step's largest error of 0.25 s means and of
single samples from 0.5 s after it (% of the step) and its time to half the step; each
sine's amplitude (published / applied) and lag (ms), where the loop takes at least 4
samples a period; the training profile's RMSE over the force axes (N).

    python -m benchmarks.accuracy.creep_trade           # the docs' figures
    python -m benchmarks.accuracy.creep_trade --quick --out DIR  # one setting (regenerate --quick)
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from benchmarks.accuracy.creep import (
    HARSH,
    STEP_N,
    Setting,
    Sine,
    Training,
    calibrated_part,
    run,
    scene,
    sine_figures,
    step_figures,
)
from benchmarks.common import FULL_CHIP, RESULTS  # FULL_CHIP: the settings of docs/results/tradeoff.md
from ftsensord.acquire.board import bus_timing
from ftsensord.acquire.bound import cycle_bound
from ftsensord.config.file import builtin_path, load_config
from ftsensord.processing.creep import CreepCompensation
from ftsensord.processing.pipeline import _BREAKS_MEMORY  # the stage's rule of what a sample keeps out
from ftsensord.sim.memory import DEFAULT_RELAXATION

DOCS = RESULTS
SCHEDULERS = ("naive", "overlapped", "burst")
#: The part: the default scene's own sensor1 (seed 1), with the default series, calibrated by the
#: documented commands (`creep.calibrated_part`).
PART = 1
#: A sine is judged where the loop takes this many samples a period or more: fewer, and the
#: fitted amplitude and phase are the sampling's (at 2 a period, Nyquist, nothing at all).
MIN_SAMPLES_A_PERIOD = 4


@dataclass(frozen=True)
class Segment:
    start_s: float
    end_s: float
    load: object  # wrench(t) -> (6,)


class Profile:
    """Segments one after another, rest between them: the load of the segment ``t`` is in."""

    def __init__(self, segments: list[Segment]):
        self.segments = segments

    def wrench(self, t: float) -> np.ndarray:
        for s in self.segments:
            if s.start_s <= t < s.end_s:
                return s.load.wrench(t)  # type: ignore[attr-defined]
        return np.zeros(6)


class Held:
    """``STEP_N`` on Fx from ``start_s`` on (the profile ends it)."""

    def __init__(self, start_s: float):
        self.start_s = start_s

    def wrench(self, t: float) -> np.ndarray:
        return np.array([STEP_N, 0, 0, 0, 0, 0]) if t >= self.start_s else np.zeros(6)


def profile(quick: bool) -> tuple[Profile, dict]:
    """The profile and where each part of it is (s): sines (f, start, end), the step (start,
    end), the training (start, end)."""
    t = 1.0
    sines, segments = [], []
    for f in (0.5, 2.0) if quick else (0.5, 1.0, 2.0, 5.0):
        length = 1.0 + max(3.0 if quick else 4.0, (2 if quick else 4) / f)  # a second in, then whole periods
        segments.append(Segment(t, t + length, Sine(np.array([STEP_N, 0, 0, 0, 0, 0]), f, t)))
        sines.append((f, t, t + length))
        t += length + 1.0
    step = (t + 1.0, t + 1.0 + (6.0 if quick else 30.0))  # a second at rest before it: the tare's
    segments.append(Segment(step[0], step[1], Held(step[0])))
    training = (step[1] + 1.0, step[1] + (5.0 if quick else 13.0))
    segments.append(Segment(training[0], training[1], Training(training[0])))
    return Profile(segments), {"sines": sines, "step": step, "training": training, "end": training[1] + 0.5}


def compensated(w: np.ndarray, flags: list[int], cal, rate_hz: float) -> np.ndarray:
    """The daemon's stage over the published samples in order, each with its flags."""
    stage = CreepCompensation(cal.silicone, rate_hz)
    return np.array([stage.apply(y, not f & _BREAKS_MEMORY) for y, f in zip(w, flags)])


def figures(t: np.ndarray, w: np.ndarray, truth: np.ndarray, where: dict, rate_hz: float) -> dict:
    """The held step's (means %, single samples %, to half ms), each sine's (amplitude, lag ms)
    or None, and the training's RMSE (N)."""
    a, b = where["step"]
    sel = (t >= a - 1.5) & (t < b)
    step = step_figures(t[sel], w[sel], truth[sel], a)
    sines = []
    for f, start, end in where["sines"]:
        sel = (t >= start) & (t < end)
        sines.append(sine_figures(t[sel], w[sel], f, start) if rate_hz >= MIN_SAMPLES_A_PERIOD * f else None)
    a, b = where["training"]
    sel = (
        (t >= a + 1.0) & (t < b) & np.all(np.isfinite(w), axis=1)
    )  # after the tool's first second pressing in
    training = float(np.sqrt(np.mean(np.square(w[sel, :3] - truth[sel, :3])))) if sel.any() else float("nan")
    return {"step": step, "sines": sines, "training": training}


def bound_hz(config, scheduler: str, osr: int, dig_filt: int) -> float:
    """The scheduler's computed bound at the setting on the configured bus (no read-back: the
    runs turn it off), as docs/results/tradeoff.md's rate table computes it."""
    board = bus_timing(config.bus)
    settings = replace(config.settings, osr=osr, dig_filt=dig_filt)
    return cycle_bound(
        scheduler,
        len(config.addresses),
        settings,
        board.clock_hz or config.bus_hz,
        config.bus_overhead_s if board.ioctl_s is None else board.ioctl_s,
        readback=False,
        adapter=board.adapter,
    ).rate_hz


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--quick", action="store_true", help="one setting, a short profile; written only to --out"
    )
    parser.add_argument(
        "--out",
        type=Path,
        help="folder for tradeoff-dynamic.md and tradeoff-dynamic.png "
        "(default: docs/results/; --quick: none, nothing written)",
    )
    args = parser.parse_args()
    quick = args.quick
    series = HARSH if quick else DEFAULT_RELAXATION  # quick: a creep its short profile shows
    t_start = time.monotonic()
    config = load_config(builtin_path("sim.toml"))
    chips = (
        [(3, 4)] if quick else FULL_CHIP
    )  # quick: the slow loops (CI's time), one under 4 samples a period
    load, where = profile(quick)
    results = []
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        _, _, cal = calibrated_part(quick, tmp, PART, series)
        assert cal.silicone is not None, cal.report["silicone"]
        checked = False
        for osr, dig in chips:
            for scheduler in SCHEDULERS:
                rate = (
                    math.floor(bound_hz(config, scheduler, osr, dig) * 10) / 10
                )  # 0.1 Hz below: the cycle fits
                setting = Setting(f"{osr}, {dig}", osr, dig, rate, scheduler=scheduler)
                flags: list[int] = []
                t, w, truth = run(
                    config, cal, scene(True, tmp, PART, series), load, where["end"], setting, False, flags
                )
                comp = compensated(w, flags, cal, rate)
                if not checked and scheduler == "burst":  # the stage's own, once: the same samples
                    _, w_daemon, _ = run(
                        config, cal, scene(True, tmp, PART, series), load, where["end"], setting, True
                    )
                    gap = float(np.nanmax(np.abs(w_daemon - comp)))
                    assert gap < 1e-9, f"the offline inverse departs from the daemon's stage by {gap:.3g} N"
                    checked = True
                flagged = sum(bool(f & _BREAKS_MEMORY) for f in flags)
                results.append(
                    (
                        osr,
                        dig,
                        scheduler,
                        rate,
                        len(t),
                        flagged,
                        figures(t, w, truth, where, rate),
                        figures(t, comp, truth, where, rate),
                    )
                )
                print(
                    f"{osr}, {dig} {scheduler} {rate} Hz: {time.monotonic() - t_start:.0f} s", file=sys.stderr
                )
    text = report(results, where, quick)
    print(text)
    if args.out is not None or not quick:
        out = args.out or DOCS
        (out / "tradeoff-dynamic.md").write_text(text)
        plot(results, out / "tradeoff-dynamic.png")
    return 0


def report(results: list, where: dict, quick: bool) -> str:
    freqs = [f for f, _, _ in where["sines"]]
    lines = [
        "# The trade, dynamic: moving loads at each setting and scheduler",
        "",
        f"Made by `python -m benchmarks.accuracy.creep_trade`{' --quick' if quick else ''}: the part of "
        "docs/results/silicone-figures.md (sensor1 of the default scene with "
        + ("the default series" if not quick else f"the quick mode's series {[list(p) for p in HARSH]}")
        + ", calibrated with its "
        "step-and-hold), the linear estimator, averaging 1, each loop at its scheduler's computed bound, one "
        f"profile of {where['end']:.0f} s: 2 N sines on Fx at {', '.join(f'{f:g}' for f in freqs)} Hz, a 2 N "
        f"step on Fx held {where['step'][1] - where['step'][0]:.0f} s, the training-like profile. Each cell "
        "is without / with the compensation. Step: the largest |error| from 0.5 s after it of 0.25 s means "
        "and of single samples (% of the step; the aim: 2 %), and the time to half the step (ms). "
        "nan: the loop, under 1 Hz, has no sample in the second before the step to tare on. "
        "Sines: amplitude published / applied and lag (ms), where the loop takes 4 samples a period or more "
        "(else -). Training: RMSE over the force axes (N). Samples flagged: those the stage keeps out of its "
        "state (a chip missing, stale, saturated or left out, inconsistent, fallen back, invalid).",
        "",
        "| OSR, DIG_FILT | scheduler | rate (Hz) | samples (flagged) | step, means (%) | step, single (%) | "
        "to half (ms) | " + " | ".join(f"{f:g} Hz amplitude; lag (ms)" for f in freqs) + " | training (N) |",
        "|---|---|---|---|---|---|---|" + "---|" * len(freqs) + "---|",
    ]
    for osr, dig, scheduler, rate, n, flagged, raw, comp in results:

        def pair(key: int, raw: dict = raw, comp: dict = comp) -> str:
            return f"{raw['step'][key]:.2f} / {comp['step'][key]:.2f}"

        def sine(k: int, raw: dict = raw, comp: dict = comp) -> str:
            if raw["sines"][k] is None:
                return "-"
            return (
                f"{raw['sines'][k][0]:.3f} / {comp['sines'][k][0]:.3f}; "
                f"{raw['sines'][k][1]:.0f} / {comp['sines'][k][1]:.0f}"
            )

        lines.append(
            f"| {osr}, {dig} | {scheduler} | {rate:.1f} | {n} ({flagged}) | {pair(0)} | {pair(1)} | "
            f"{raw['step'][2]:.0f} / {comp['step'][2]:.0f} | "
            + " | ".join(sine(k) for k in range(len(freqs)))
            + f" | {raw['training']:.4f} / {comp['training']:.4f} |"
        )
    lines += ["", "The figures are on a virtual clock: the host's load does not enter them."]
    return "\n".join(lines) + "\n"


def plot(results: list, path: Path) -> None:
    """Against the loop's rate: the held step's single-sample error (noise), the 2 Hz sine's lag
    and the training RMSE, each scheduler a marker, with (filled) and without (open) the compensation."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib is missing (pip install 'ftsensord[plot]'): no plot", file=sys.stderr)
        return
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.2))
    markers = {"naive": "s", "overlapped": "^", "burst": "o"}
    panels = (
        ("held step, single samples (% of 2 N)", lambda r: r["step"][1]),
        (
            "2 Hz sine: lag (ms)",
            lambda r: r["sines"][2][1] if len(r["sines"]) > 2 and r["sines"][2] else np.nan,
        ),
        ("training-like profile: RMSE (N)", lambda r: r["training"]),
    )
    for ax, (title, value) in zip(axes, panels):
        for scheduler, marker in markers.items():
            rows = [r for r in results if r[2] == scheduler]
            rate = [r[3] for r in rows]
            ax.scatter(
                rate,
                [value(r[6]) for r in rows],
                marker=marker,
                facecolors="none",
                edgecolors="C0",
                label=f"{scheduler}, without",
            )
            ax.scatter(
                rate, [value(r[7]) for r in rows], marker=marker, color="C1", label=f"{scheduler}, with"
            )
        if not any(
            np.isfinite(value(r[k])) for r in results for k in (6, 7)
        ):  # --quick: a figure not measured
            ax.text(0.5, 0.5, "not measured", ha="center", transform=ax.transAxes)
            continue
        ax.set_xscale("log")
        ax.set_xlabel("loop rate (Hz)")
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    sys.exit(main())
