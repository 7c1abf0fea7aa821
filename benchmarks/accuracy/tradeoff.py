"""Speed against accuracy: writes docs/results/tradeoff.md and docs/results/tradeoff.png.

For chip settings (OSR, DIG_FILT across the permitted range), averaging windows,
schedulers and estimators:

- the computed bound on the rate, and the rate achieved in real time on the configured bus
  (`ftsensord.acquire.reader.Reader` cycling at its bound; the simulated bus spends real wire time);
- wrench noise at rest (RMS) and, on the simulated bus, accuracy against the scene's truth
  (RMSE) at small loads (<= 2 N, 0.02 Nm), inside the calibration's range (the paper's poses'
  loads) and at large loads (|F| 10 to 50 N, torques to 0.2 Nm), on a virtual clock (the
  chips' noise and quantisation included; averaging N means the mean of N readings a
  published sample);
- the daemon's own CPU per cycle (16 chips, decode, estimate, publish) on a bus that
  answers instantly, so the bus's cost is not counted;
- the latency from a sample's timestamp to a subscriber's receipt over loopback.

The bus, chips and first sensor's calibration come from a configuration, so the same command
runs on hardware: with ``--config`` naming an ``i2c:N`` bus it measures rates, noise at rest
(leave the sensor unloaded), CPU and latency, and leaves the truth columns empty (a real
bus has no truth; the rig's validation set gives that, docs/guide/calibration.md).

    python -m benchmarks.accuracy.tradeoff                      # the docs' figures (about 5 minutes)
    python -m benchmarks.accuracy.tradeoff --quick --out DIR    # CI: a few settings, under a minute
    python -m benchmarks.accuracy.tradeoff --config /etc/ftsensord/ftsensord.toml --out /tmp/board  # on a board

The plot needs the `plot` extra.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path
from unittest import mock

import numpy as np
import zmq

from benchmarks.common import FULL_CHIP, RESULTS, Capture, InstantBus
from ftsensord.acquire.board import bus_timing
from ftsensord.acquire.bound import cycle_bound
from ftsensord.acquire.bus import open_bus, parse_bus_spec
from ftsensord.acquire.health import stuck_cycles_for
from ftsensord.acquire.reader import Reader
from ftsensord.chip import mlx90393 as mlx
from ftsensord.chip.driver import MLX90393
from ftsensord.chip.i2c import Bus
from ftsensord.config.file import Config, builtin_path, load_config
from ftsensord.daemon.daemon import Daemon
from ftsensord.model.linear import SENSOR_RANGE
from ftsensord.protocol import wire
from ftsensord.sim import (
    MonotonicClock,
    PhysicalScene,
    VirtualClock,
    default_scene,
    load_scene,
    simulated_bus,
)
from ftsensord.sim.loads import StaticLoad, paper_plan
from ftsensord.testing.harness import start_daemon, stop

ADDRESSES = list(range(0x0C, 0x1C))  # the instant bus's chips: the default scene's
NAN = float("nan")
#: What benchmarks/accuracy/creep.py measured of moving loads on a silicone with a memory (the loops
#: of this file's rows; its own figures in docs/results/silicone-figures.md).
SILICONE = """## Moving loads: the silicone's memory

Every row above holds its load still. A silicone that relaxes (docs/design/physics.md, "The
silicone's memory") makes a moving load and a held one read differently.
`python -m benchmarks.accuracy.creep_trade` runs every chip setting above under each scheduler at its
computed bound (read-back off: burst reaches 214 Hz at OSR 0-2) on a part with the default
series, linear estimator, one 74 s profile (2 N sines at 0.5-5 Hz, a 2 N step held 30 s,
the training-like profile), with and without the compensation: 30 loops, 294 to 15680
samples each, in [tradeoff-dynamic.md](tradeoff-dynamic.md) and
[tradeoff-dynamic.png](tradeoff-dynamic.png); `python -m benchmarks.accuracy.creep` adds the
nonlinear estimator and averaging at the default loop (docs/results/silicone-figures.md). What
decides the trade there:

- The compensation first: without it every loop reads a moving load 16 % low and a held
  step 11.5-15 % off (the calibration's K is the long-term stiffness); with it the sines
  read 0.976-0.985 of the load under overlapped and burst wherever no sample is flagged (K A's
  own -2 % on Fx) and the training RMSE halves (0.124-0.126 N to 0.061-0.066 N at 88-214 Hz).
- A faster rate wins the moving load: the lag of a 2 Hz sine is 5-6 ms at 88-214 Hz, 8 ms at
  44-59 Hz, 10 ms at 26-30 Hz and 35-90 ms under the naive scheduler's 8.8-22 Hz; the
  training RMSE, compensated,
  0.061-0.064 N at 88 Hz and over, 0.069-0.072 at 44-59 Hz, 0.087-0.090 at 26-30 Hz, 0.18 and
  more below 10 Hz. The held step's 0.25 s means are best at the fastest loops too (1.70-1.82 %
  under burst at 170-214 Hz and 1.74-1.93 % under overlapped at 96-116 Hz, within the aim of
  2 %; 2.1-2.5 % under overlapped at 88, 105 and 138 Hz, the noisier samples; 2.4-3.8 % at
  59 Hz and below, fewer samples a window).
- Noise wins the held load sample by sample: a single sample of the held step is 7.8-8.1 %
  off at OSR 0, DIG_FILT 2, 5.3-6.3 % at OSR 1-2, DIG_FILT 1-3, and 3.8-4.6 % at DIG_FILT
  4-7, where the loop is 4-59 Hz.
- The scheduler: naive is too slow for any moving load (1.8-22 Hz, the chips read one after
  another) and has 9-97 % of its samples flagged `inconsistent` + `degraded`; overlapped and
  burst do alike where both reach 88 Hz or more.
- **Where the compensation fails: samples flagged while the load moves.** The consistency
  check flags a moving load at the longest conversions (burst at OSR 2-3, DIG_FILT 4-7: the
  5 Hz sine at 59 and 30 Hz, the 2 Hz one at 8 Hz, the 1 Hz one and the held step's creep at
  4-8 Hz; 116-340 of those loops' samples) and
  under the naive scheduler (its chips sampled up to a cycle apart). The stage keeps every
  flagged sample out of its state (docs/guide/calibration.md) and coasts on the last clean load,
  so those stretches are not compensated: 0.76-0.86 of the sine's amplitude and 13-15 % off
  the held step at 4-8 Hz, as without it.
  The overlapped scheduler at the same settings has none flagged and is compensated
  throughout."""


@dataclass
class Row:
    osr: int
    dig_filt: int
    averaging: int
    estimator: str
    noise_n: float
    noise_nm: float
    rmse_small: float
    rmse_cal: float
    rmse_large: float
    rmse_large_nm: float
    flagged_large: int = 0  # large-load samples flagged (beyond overload): degraded, extrapolated...
    invalid_large: int = 0  # of them, published as NaN (too many chips saturated)
    n_large: int = 0

    @property
    def tconvm_us(self) -> float:
        return mlx.tconvm_us(self.osr, self.dig_filt)


def scene_name(config: Config) -> str:
    """What the simulated bus's scene is, for the docs: the default (the room and the part)
    or the file the configuration names."""
    _, arg = parse_bus_spec(config.bus)
    return (
        f"`{arg}`"
        if arg
        else (
            "the default (ftsensord/data/scene-default.toml: two as-built sensors in the "
            "Earth's field, calibrated on it by the packaged procedure)"
        )
    )


def bench_bus(
    config: Config, clock: VirtualClock | MonotonicClock, seed: int = 0
) -> tuple[Bus, PhysicalScene | None]:
    """The configured bus, and the scene behind it when it is simulated with loads to set."""
    kind, arg = parse_bus_spec(config.bus)
    if kind == "i2c":
        return open_bus(config.bus), None
    scene = load_scene(arg) if arg else default_scene()
    bus = simulated_bus(scene, clock=clock, bus_hz=config.bus_hz, seed=seed)
    return bus, scene if isinstance(scene, PhysicalScene) else None


def achieved_rate(
    config: Config, scheduler: str, settings: mlx.Settings, seconds: float
) -> tuple[float, float]:
    """(bound, achieved) in Hz: the reader cycling on deadlines at its bound, in real time."""
    addresses = config.addresses
    board = bus_timing(config.bus)  # a simulated board's adapter and costs; a real one's driver
    bound = cycle_bound(
        scheduler,
        len(addresses),
        settings,
        board.clock_hz or config.bus_hz,
        config.bus_overhead_s if board.ioctl_s is None else board.ioctl_s,
        adapter=board.adapter,
    )
    bus, _ = bench_bus(config, MonotonicClock())
    reader = Reader(
        bus,
        [MLX90393(bus, a, sleep=bus.sleep) for a in addresses],
        scheduler,
        settings,
        config.bus_hz,
        config.bus_overhead_s,
        readback_every=1 if scheduler != "burst" else 100,
    )
    reader.start()
    time.sleep(0.05)
    deadline = t0 = time.monotonic()
    cycles = 0
    while time.monotonic() - t0 < seconds:
        reader.read()
        reader.upkeep()
        cycles += 1
        deadline += bound.cycle_s
        pause = deadline - time.monotonic()
        if pause > 0:
            time.sleep(pause)
        else:
            deadline = time.monotonic()  # late: never make up cycles by a burst
    rate = cycles / (time.monotonic() - t0)
    bus.close()
    return bound.rate_hz, rate


def loads(kind: str, n: int, rng: np.random.Generator) -> list[np.ndarray]:
    if kind == "cal":
        return [p.wrench() for p, s in paper_plan("six-axis", n_fit=n, n_validation=0)]
    out = []
    for _ in range(n):
        w = rng.uniform(-1, 1, 6)
        if kind == "small":
            w *= np.array([2, 2, 2, 0.02, 0.02, 0.02])
        else:  # |F| from 10 N to the range, torques to the range
            f = w[:3] / np.linalg.norm(w[:3]) * rng.uniform(10, 50)
            w = np.concatenate([np.clip(f, -SENSOR_RANGE[:3], SENSOR_RANGE[:3]), w[3:] * SENSOR_RANGE[3:]])
        out.append(w)
    return out


def accuracy(config: Config, settings: mlx.Settings, averaging: int, n_loads: int) -> list[Row]:
    """Noise and RMSE of what the daemon publishes for the first sensor, with each estimator
    its calibration has, at one chip setting and averaging window; on a virtual clock.

    A sample is read after ``averaging`` cycles at a load, so it is the mean of that many
    fresh estimates, flags as the daemon sets them. RMSE is over the samples the daemon
    publishes with values (an invalid one is NaN and counted apart); NaN where the bus has
    no truth.
    """
    sensor = config.sensors[0]
    estimators = ["linear"] + (["nonlinear"] if sensor.calibration.nonlinear is not None else [])
    rows = []
    for estimator in estimators:
        bus, scene = bench_bus(config, VirtualClock(), seed=11)
        cfg = replace(
            config,
            settings=settings,
            averaging=averaging,
            stuck_cycles=stuck_cycles_for(settings),
            scheduler="overlapped",
            readback_every=0,
            temperature_every=0,
            tool_poses={},
            sensors=[replace(s, estimator=estimator if s is sensor else "linear") for s in config.sensors],
        )
        out = Capture()
        daemon = Daemon(cfg, bus, out, None, clock=bus.monotonic)  # type: ignore[arg-type]
        daemon.start()

        def read(w: np.ndarray | None, scene=scene, bus=bus, daemon=daemon, out=out) -> wire.Sample:
            if scene is not None and w is not None:
                scene.set_load(0, StaticLoad(w))
            bus.sleep(0.02)
            for _ in range(averaging):
                daemon.cycle()
            return out.last[f"wrench/{sensor.name}"]

        rng = np.random.default_rng(5)
        rest = np.array([read(np.zeros(6)).values for _ in range(max(20, 120 // averaging))])
        noise = np.nanstd(rest, axis=0)
        samples = (
            {kind: [(read(w), w) for w in loads(kind, n_loads, rng)] for kind in ("small", "cal", "large")}
            if scene is not None
            else {}
        )
        bus.close()

        def rmse(kind: str, axes: slice, samples: dict = samples) -> float:
            errors = [
                s.values[axes] - w[axes] for s, w in samples.get(kind, []) if not s.flags & wire.FLAG_INVALID
            ]
            return float(np.sqrt(np.mean(np.square(errors)))) if errors else NAN

        large = [s.flags for s, _ in samples.get("large", [])]
        rows.append(
            Row(
                settings.osr,
                settings.dig_filt,
                averaging,
                estimator,
                float(np.linalg.norm(noise[:3])),
                float(np.linalg.norm(noise[3:])),
                rmse("small", slice(0, 3)),
                rmse("cal", slice(0, 3)),
                rmse("large", slice(0, 3)),
                rmse("large", slice(3, 6)),
                flagged_large=sum(bool(f & ~wire.FLAG_OVERLOAD) for f in large),
                invalid_large=sum(bool(f & wire.FLAG_INVALID) for f in large),
                n_large=len(large),
            )
        )
    return rows


def daemon_cpu_us(estimator: str, cycles: int) -> float:
    """CPU time (us) of one daemon cycle: 16 chips, two sensors, tip, publish."""
    with tempfile.TemporaryDirectory() as tmp:
        config = load_config(builtin_path("sim.toml"))
        for s in config.sensors:
            s.estimator = estimator
        ctx = zmq.Context()
        pub = ctx.socket(zmq.PUB)
        pub.bind(f"ipc://{tmp}/pub")
        daemon = Daemon(config, InstantBus(config), pub, None)
        daemon.start()
        for _ in range(20):
            daemon.cycle()
        t0 = time.process_time()
        for _ in range(cycles):
            daemon.cycle()
        cpu = (time.process_time() - t0) / cycles
        pub.close(linger=0)
        ctx.term()
    return cpu * 1e6


def latency_us(config: Config, seconds: float) -> tuple[float, float, float]:
    """Sample timestamp to a subscriber's receipt (us), the daemon over ipc loopback."""
    from ftsensord.client import Subscriber

    with tempfile.TemporaryDirectory() as tmp:
        proc, notify = start_daemon(config.path, Path(tmp))
        try:
            # The endpoint the daemon's environment gives (its runtime folder in tmp).
            with mock.patch.dict(os.environ, {"XDG_RUNTIME_DIR": tmp}):
                os.environ.pop("RUNTIME_DIRECTORY", None)
                endpoint = load_config(config.path).publish[0]
            delays = []
            with Subscriber(endpoint, [f"wrench/{config.sensors[0].name}"]) as sub:
                end = time.monotonic() + seconds
                while time.monotonic() < end:
                    s = sub.receive(timeout_s=2)
                    if s is not None:
                        delays.append(time.monotonic() - s.t_mono)
        finally:
            stop(proc, notify)
    d = np.array(delays[10:]) * 1e6
    return float(np.percentile(d, 50)), float(np.percentile(d, 99)), float(d.max())


def pareto(points: list[tuple[float, float, object]]) -> list[object]:
    """Items not beaten on both rate (higher) and error (lower)."""
    return [
        p
        for p in points
        if not any(q[0] >= p[0] and q[1] <= p[1] and (q[0], q[1]) != (p[0], p[1]) for q in points)
    ]


QUICK_CHIP = [(1, 2), (3, 4)]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--quick", action="store_true", help="a few settings, under a minute; written only to --out"
    )
    parser.add_argument(
        "--config",
        type=Path,
        default=builtin_path("sim.toml"),
        help="the bus, chips and calibration to measure (default: the simulated sensors)",
    )
    parser.add_argument(
        "--out",
        type=Path,
        help="folder for tradeoff.md and tradeoff.png (default: docs/results/; --quick: none, "
        "nothing written)",
    )
    args = parser.parse_args()
    quick = args.quick
    config = load_config(args.config)
    chip = QUICK_CHIP if quick else FULL_CHIP
    windows = [1, 4] if quick else [1, 4, 16]
    t_start = time.monotonic()
    rates = {}
    for osr, dig in chip:
        settings = replace(config.settings, osr=osr, dig_filt=dig)
        for scheduler in ("naive", "overlapped", "burst"):
            rates[(osr, dig, scheduler)] = achieved_rate(config, scheduler, settings, 0.3 if quick else 1.5)
    rows = [
        r
        for osr, dig in chip
        for n in windows
        for r in accuracy(config, replace(config.settings, osr=osr, dig_filt=dig), n, 4 if quick else 20)
    ]
    cpu = {e: daemon_cpu_us(e, 50 if quick else 500) for e in ("linear", "nonlinear")}
    lat = latency_us(config, 3 if quick else 15)
    elapsed = time.monotonic() - t_start
    report = render(config, chip, rates, rows, cpu, lat, quick, elapsed)
    print(report)
    if args.out is not None or not quick:
        out = args.out or RESULTS
        out.mkdir(parents=True, exist_ok=True)
        (out / "tradeoff.md").write_text(report)
        plot(config, rows, rates, out / "tradeoff.png")
    return 0


def best_rate(rates: dict, osr: int, dig: int) -> tuple[str, float, float]:
    s = max(("naive", "overlapped", "burst"), key=lambda s: rates[(osr, dig, s)][1])
    return s, *rates[(osr, dig, s)]


def has_truth(rows: list[Row]) -> bool:
    return not np.isnan(rows[0].rmse_cal)


def error_of(r: Row, truth: bool) -> float:
    """What the Pareto front minimises: RMSE against the truth, or (on a real bus) noise at rest."""
    return r.rmse_cal if truth else r.noise_n


def machine() -> str:
    return f"{os.cpu_count()}-core {platform.machine()} machine, Python {platform.python_version()}"


def render(config: Config, chip, rates, rows, cpu, lat, quick, elapsed) -> str:
    n_chips = len(config.addresses)
    truth = has_truth(rows)
    error_name = "RMSE inside the calibration range (N)" if truth else "noise F at rest (N)"
    out = [
        "# Speed against accuracy",
        "",
        f"Made by `python -m benchmarks.accuracy.tradeoff` ({'quick mode' if quick else 'full run'}, {elapsed:.0f} s) "
        f"on a {machine()}; {n_chips} chips on `{config.bus}` at {config.bus_hz / 1e3:.0f} kHz"
        + (f"; scene: {scene_name(config)}." if truth else "."),
        "",
        "## Rate: the computed bound and what the loop achieves in real time",
        "",
        "| OSR, DIG_FILT | TCONVM (us) | naive bound / achieved (Hz) | overlapped bound / achieved (Hz) | "
        "overlapped ratio | burst bound / achieved (Hz) |",
        "|---|---|---|---|---|---|",
    ]
    for osr, dig in chip:
        cells = []
        for s in ("naive", "overlapped", "burst"):
            b, a = rates[(osr, dig, s)]
            cells.append(f"{b:.1f} / {a:.1f}")
        b, a = rates[(osr, dig, "overlapped")]
        naive = rates[(osr, dig, "naive")][1]
        out.append(
            f"| {osr}, {dig} | {mlx.tconvm_us(osr, dig):.0f} | {cells[0]} | {cells[1]} | "
            f"{a / b * 100:.1f} % of bound, {a / naive:.1f}x naive | {cells[2]} |"
        )
    out += [
        "",
        "The overlapped ratio is achieved over bound in the same run, and over the naive "
        "scheduler's achieved rate.",
        "",
        "## Accuracy: noise at rest and error against the scene's truth",
        "",
        "Noise: RMS of |F| and |M| at rest; RMSE over the force axes (N) and, at large loads, the torque axes "
        "(mNm). Small: <= 2 N; calibration range: the paper's poses' loads; large: |F| 10-50 N. "
        "Effective rate: the fastest scheduler's achieved rate over the averaging window. What the daemon "
        "publishes for sensor1, flags and all; RMSE over the samples published with values. Large loads "
        "flagged: samples the daemon marked (saturated chips left out, degraded, a nonlinear fall-back to "
        "K A, a linear estimate beyond the calibration's loads), of which invalid (published as NaN, left "
        "out of the RMSE)." + ("" if truth else " A real bus has no truth: the RMSE columns are empty."),
        "",
        "| OSR, DIG_FILT | averaging | estimator | effective rate (Hz) | noise F (N) | noise M (mNm) | "
        "RMSE small (N) | RMSE cal. range (N) | RMSE large (N) | RMSE large (mNm) | large flagged / invalid |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    points = []
    for r in rows:
        sched, _, achieved = best_rate(rates, r.osr, r.dig_filt)
        effective = achieved / r.averaging
        points.append((effective, error_of(r, truth), r))
        out.append(
            f"| {r.osr}, {r.dig_filt} | {r.averaging} | {r.estimator} | {effective:.1f} ({sched}) | "
            f"{r.noise_n:.4f} | {r.noise_nm * 1e3:.2f} | {r.rmse_small:.4f} | {r.rmse_cal:.4f} | "
            f"{r.rmse_large:.3f} | {r.rmse_large_nm * 1e3:.2f} | "
            f"{r.flagged_large} / {r.invalid_large} of {r.n_large} |".replace("nan", "-")
        )
    front = pareto(points)
    if truth:
        out += [
            "",
            "Reading the table: the linear model's error inside the calibration range is its own (a first-order "
            "map of a 1/r^3 field), so averaging, which only lowers noise, leaves it flat; the nonlinear "
            "estimator's error is mostly noise, and falls with averaging and longer conversions. Beyond the "
            "calibration's loads K A extrapolates and its error grows with the load; the daemon flags such "
            "samples `extrapolated`. Where loads leave the calibration range, use the nonlinear estimator (or "
            "calibrate with larger loads).",
        ]
    out += [
        "",
        f"## The Pareto front (effective rate against {error_name})",
        "",
        f"| effective rate (Hz) | {error_name} | setting |",
        "|---|---|---|",
    ]
    for p in sorted(front, key=lambda p: -p[0]):
        r = p[2]
        out.append(
            f"| {p[0]:.1f} | {p[1]:.4f} | OSR {r.osr}, DIG_FILT {r.dig_filt}, averaging {r.averaging}, "
            f"{r.estimator} |"
        )
    fast = [p for p in points if p[0] >= 100]
    if fast:
        best = min(fast, key=lambda p: p[1])[2]
        sched = best_rate(rates, best.osr, best.dig_filt)[0]
        out += [
            "",
            f"**Recommended for 100 Hz with {n_chips} chips**: OSR {best.osr}, DIG_FILT {best.dig_filt}, "
            f"averaging {best.averaging}, {sched} scheduler, {best.estimator} estimator: the setting with the "
            f"lowest {error_name} whose effective rate reaches 100 Hz.",
        ]
    else:
        out += ["", f"No setting measured reaches 100 Hz with {n_chips} chips on this bus."]
    n_sensors = len(config.sensors)
    per_sensor = (cpu["nonlinear"] - cpu["linear"]) / 2  # the CPU run has the default two sensors
    out += ["", *SILICONE.splitlines()]  # creep.py's figures: their trade, kept with this file's
    out += [
        "",
        "## Cost and latency",
        "",
        f"- daemon CPU per cycle (the default two sensors of 8 chips: decode, estimate, tip, publish; a bus "
        f"that answers at once): linear {cpu['linear']:.0f} us, nonlinear {cpu['nonlinear']:.0f} us; at 100 Hz "
        f"{cpu['linear'] / 100:.1f} % and {cpu['nonlinear'] / 100:.1f} % of one core; the nonlinear estimate "
        f"costs {per_sensor:.0f} us a sensor more than K A",
        f"- sample timestamp to subscriber receipt over ipc, the daemon at {config.rate_hz:g} Hz "
        f"({n_sensors} sensors): p50 {lat[0]:.0f} us, p99 {lat[1]:.0f} us, max {lat[2]:.0f} us",
    ]
    lin, nonl = (
        [
            r
            for r in rows
            if r.estimator == e
            and r.averaging == 1
            and (r.osr, r.dig_filt) == (config.settings.osr, config.settings.dig_filt)
        ]
        for e in ("linear", "nonlinear")
    )
    if truth and lin and nonl:
        li, n = lin[0], nonl[0]
        out += [
            f"- at the configured chip setting, large loads: linear {li.rmse_large:.3f} N / "
            f"{li.rmse_large_nm * 1e3:.1f} mNm, nonlinear {n.rmse_large:.3f} N / {n.rmse_large_nm * 1e3:.1f} mNm: "
            f"{li.rmse_large / n.rmse_large:.0f}x and {li.rmse_large_nm / n.rmse_large_nm:.0f}x lower"
        ]
    ratios = {
        (osr, dig): rates[(osr, dig, "overlapped")][1] / rates[(osr, dig, "overlapped")][0]
        for osr, dig in chip
    }
    worst = min(ratios, key=ratios.__getitem__)
    targets = [
        (
            "overlapped scheduler at >= 90 % of the bound (worst setting)",
            ratios[worst] * 100,
            90,
            ">=",
            f"{ratios[worst] * 100:.1f} % at OSR {worst[0]}, DIG_FILT {worst[1]}",
        ),
        (
            "nonlinear estimate <= 1000 us of CPU a sensor a sample",
            per_sensor,
            1000,
            "<=",
            f"{per_sensor:.0f} us",
        ),
        (
            "linear daemon at 100 Hz <= 5 % of one core",
            cpu["linear"] / 100,
            5,
            "<=",
            f"{cpu['linear'] / 100:.1f} %",
        ),
        ("sample-to-subscriber latency p99 < 1000 us", lat[1], 1000, "<=", f"{lat[1]:.0f} us"),
    ]
    if truth and lin and nonl:
        gain = min(li.rmse_large / n.rmse_large, li.rmse_large_nm / n.rmse_large_nm)
        targets.insert(
            1, ("nonlinear cuts the large-load RMSE >= 5x (F and M)", gain, 5, ">=", f"{gain:.0f}x")
        )
    out += ["", "## Against the targets", "", "| target | measured | |", "|---|---|---|"]
    for name, value, goal, sense, shown in targets:
        met = value >= goal if sense == ">=" else value <= goal
        out.append(
            f"| {name} | {shown} | {'met' if met else f'missed by {abs(value - goal) / goal * 100:.0f} %'} |"
        )
    return "\n".join(out) + "\n"


def plot(config: Config, rows: list[Row], rates: dict, path: Path) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib is missing (pip install 'ftsensord[plot]'): no plot", file=sys.stderr)
        return
    truth = has_truth(rows)
    fig, ax = plt.subplots(figsize=(8, 5))
    points = []
    for est, marker in (("linear", "o"), ("nonlinear", "s")):
        for n, color in zip((1, 4, 16), ("tab:blue", "tab:orange", "tab:green")):
            sel = [r for r in rows if r.estimator == est and r.averaging == n]
            if not sel:
                continue
            xs = [best_rate(rates, r.osr, r.dig_filt)[2] / n for r in sel]
            ys = [error_of(r, truth) for r in sel]
            points += list(zip(xs, ys))
            ax.loglog(
                xs,
                ys,
                marker,
                color=color,
                mfc="none" if est == "linear" else color,
                label=f"{est}, averaging {n}",
            )
    front = sorted(pareto([(x, y, (x, y)) for x, y in points]), key=lambda p: p[0])
    ax.loglog([p[0] for p in front], [p[1] for p in front], "k--", lw=1, label="Pareto front")
    ax.axvline(100, color="grey", lw=1)
    ax.set_xlabel("effective rate (Hz): achieved rate / averaging")
    ax.set_ylabel("RMSE inside the calibration range (N)" if truth else "noise F at rest (N)")
    ax.set_title(f"{len(config.addresses)} chips, {config.bus_hz / 1e3:.0f} kHz: rate against accuracy")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    raise SystemExit(main())
