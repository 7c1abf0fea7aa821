"""Figures for a board: the CPU benchmarks where the daemon runs, its bus when there is one,
and which configurations hold 100 Hz with 20 % of the period spare.

On a Raspberry Pi (or any board), from a checkout with the package installed, the daemon
stopped (doctor takes the bus and disturbs the chips):

    python -m benchmarks.performance.board --out board.json                    # the CPU figures (about 1 min)
    python -m benchmarks.performance.board --bus /dev/i2c-1 --out board.json   # and the bus, with the chips on it

and send back ``board.json`` (it records the board's model, clock governor, Python and numpy).
It runs, pinned to one core, `cycle_cpu.py`'s measurement (the daemon's cycle less the
stand-in bus's Python, beside the minimal loop) and `nonlinear_cpu.py`'s (a load moving at
1.3 Hz, 40 % of range; at rest), and with ``--bus`` `ftsensord doctor --real-time` on it
(the adapter, its clock and ioctl cost measured, the bound and the rate held per scheduler).

The table: a cycle is its bus time (`bound.cycle_bound`'s slowest cycle: burst, 16 chips,
with and without the register read-back and the temperature cycle) plus its CPU (this host's
figures times ``--pi-factor``, a stated scale, not a measurement: 1 on the board itself,
where the bus rows use what doctor measured); it holds 100 Hz with 20 % spare when that is
at most 8 ms. The nonlinear rows add each estimating sensor's p99, the tail a cycle must fit.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import pin_to_core
from benchmarks.performance import cycle_cpu, nonlinear_cpu
from ftsensord.acquire.bound import cycle_bound
from ftsensord.chip import mlx90393 as mlx

PERIOD_MS = 10.0  # 100 Hz
SPARE = 0.2  # of the period left free: the CPU jitter and a late wake-up fit in it
#: The boards of the table: (name, adapter, ioctl cost s, I2C clock Hz). A Pi 4's adapter at
#: the ioctl costs measured on one (60-80 us), and a pessimistic board: 150 us
#: an ioctl, the clock at 250 kHz because the core clock floats (docs/results/performance.md).
BOARDS = [
    ("Pi 4, 60 us an ioctl, 400 kHz", "bcm2835", 60e-6, 400e3),
    ("Pi 4, 80 us an ioctl, 400 kHz", "bcm2835", 80e-6, 400e3),
    ("pessimistic: 150 us, 250 kHz", "bcm2835", 150e-6, 250e3),
]


#: The bus's levers of the table, (register read-back, temperatures read): the default, the
#: read-back off (`readback_every = 0`), both off (`temperature_every = 0` too).
BUS_LEVERS = [(True, True), (False, True), (False, False)]


def facts() -> dict[str, Any]:
    """What the figures were measured on."""

    def read(path: str) -> str | None:
        try:
            return Path(path).read_text().strip("\0\n ")
        except OSError:
            return None

    return {
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "model": read("/proc/device-tree/model"),
        "governor": read("/sys/devices/system/cpu/cpu0/cpufreq/scaling_governor"),
        "max_khz": read("/sys/devices/system/cpu/cpu0/cpufreq/scaling_max_freq"),
        "load_1min": os.getloadavg()[0],
        "uptime": read("/proc/uptime"),
    }


def configurations(cpu: dict[str, Any], nl: dict[str, Any]) -> list[tuple[str, float]]:
    """(name, CPU us a cycle on this host): the daemon's own linear cycle, plus the nonlinear
    estimate's p99 for each sensor that runs it."""
    own = cpu["daemon_own_us"]
    moving, rest = nl["moving"]["cpu_us"]["p99"], nl["rest"]["cpu_us"]["p99"]
    return [
        ("linear (default)", own),
        ("nonlinear, one sensor, load moving", own + moving),
        ("nonlinear, both sensors, at rest", own + 2 * rest),
        ("nonlinear, both sensors, load moving", own + 2 * moving),
    ]


def table(
    cpu: dict[str, Any], nl: dict[str, Any], factor: float, boards: list[tuple[str, str | None, float, float]]
) -> list[dict[str, Any]]:
    rows = []
    for board, adapter, ioctl_s, clock_hz in boards:
        for readback, temperature in BUS_LEVERS:
            bus_ms = (
                cycle_bound(
                    "burst",
                    16,
                    mlx.Settings(),
                    clock_hz,
                    ioctl_s,
                    readback=readback,
                    temperature=temperature,
                    adapter=adapter,
                ).cycle_s
                * 1e3
            )
            for name, us in configurations(cpu, nl):
                cycle_ms = bus_ms + us * factor * 1e-3
                rows.append(
                    {
                        "board": board,
                        "readback": readback,
                        "temperature": temperature,
                        "configuration": name,
                        "bus_ms": bus_ms,
                        "cpu_ms": us * factor * 1e-3,
                        "cycle_ms": cycle_ms,
                        "spare": 1 - cycle_ms / PERIOD_MS,
                        "holds": cycle_ms <= (1 - SPARE) * PERIOD_MS,
                    }
                )
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--bus", help="a real bus to measure too (e.g. /dev/i2c-1); the daemon must be stopped"
    )
    parser.add_argument(
        "--pi-factor",
        type=float,
        default=1.0,
        help="scale the CPU figures by this (a stated estimate for another CPU; 1: this one)",
    )
    parser.add_argument("--cycles", type=int, default=1000, help="cycles a round of cycle_cpu (default 1000)")
    parser.add_argument("--rounds", type=int, default=7, help="rounds of cycle_cpu (default 7)")
    parser.add_argument("--quick", action="store_true", help="few samples (CI): the structure, not figures")
    parser.add_argument("--out", help="write the JSON here (send it back)")
    args = parser.parse_args()
    cycles, rounds, periods, loops = (100, 3, 2, 1) if args.quick else (args.cycles, args.rounds, 13, 5)
    cpu_core = pin_to_core(None)
    out: dict[str, Any] = {
        "facts": facts(),
        "pinned_cpu": cpu_core,
        "pi_factor": args.pi_factor,
        "quick": args.quick,
    }
    out["cycle_cpu"] = cpu = cycle_cpu.measure(cycles, rounds)
    out["nonlinear"] = nl = nonlinear_cpu.measure(0.4, 1.3, periods, loops)
    boards = list(BOARDS)
    if args.bus:
        from ftsensord.acquire.doctor import doctor

        out["doctor"] = d = doctor(args.bus, real_time=True)
        boards.insert(
            0, (f"this board ({args.bus}, measured)", d["adapter"], d["ioctl_us"] * 1e-6, d["clock_hz"])
        )
    out["table"] = rows = table(cpu, nl, args.pi_factor, boards)
    text = json.dumps(out, indent=2)
    if args.out:
        Path(args.out).write_text(text + "\n")
    print(
        f"{out['facts']['model'] or platform.machine()}, Python {platform.python_version()}, load "
        f"{out['facts']['load_1min']:.2f}; CPU figures x {args.pi_factor:g}"
    )
    print(
        f"reference {cpu['reference_us']:.1f} us, daemon's own cycle {cpu['daemon_own_us']:.1f} us "
        f"({cpu['ratio']:.2f}x); nonlinear a sensor: moving p99 {nl['moving']['cpu_us']['p99']:.0f} us, "
        f"at rest p99 {nl['rest']['cpu_us']['p99']:.0f} us"
    )
    for r in rows:
        print(
            f"  {r['board']:36s} read-back {'on ' if r['readback'] else 'off'}, "
            f"T {'on ' if r['temperature'] else 'off'}"
            f"  {r['configuration']:38s} "
            f"{r['bus_ms']:5.2f} + {r['cpu_ms']:5.2f} = {r['cycle_ms']:5.2f} ms  "
            f"{r['spare']:4.0%} spare  {'holds' if r['holds'] else 'MISSES'}"
        )
    if args.out:
        print(f"written to {args.out}: send it back with the board's model")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
