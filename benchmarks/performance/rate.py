"""Achieved rate of the daemon: 16 simulated chips on a bus that spends real wire time.

Starts `ftsensord run` with the default configuration (the simulated bus standing for a
Pi 4's adapter, 400 kHz, the scheduler the daemon chooses, 100 Hz) in a subprocess, subscribes to one
stream, and after ``--seconds`` reports from the subscriber's side: samples received, the
rate they imply (sequence numbers over the daemon's timestamps), sequence gaps, and from
the daemon's status: the bound, missed and late cycles, jitter, how long a cycle takes
(p50, p99: what it leaves of the period), and its CPU time. Run:

    python -m benchmarks.performance.rate --seconds 60 [--rate 100] [--scheduler burst] [--adapter \
        bcm2835 --ioctl-us 80 --clock-hz 250000] [--fifo 50]

With no ``--scheduler`` the daemon chooses the scheduler and read-back (`acquire.choice`).
``--fifo PRIO`` runs the daemon SCHED_FIFO at that priority (through ``chrt``), as the
systemd unit's ``--realtime 50`` asks; without it the daemon runs at the default policy,
as a user starting it by hand would.

and the figures go to docs/results/performance.md by hand, with the command line.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

from ftsensord.client import ControlClient, Subscriber
from ftsensord.testing.harness import cpu_seconds, packaged_config, start_daemon, stop


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--rate", type=float, default=100.0)
    parser.add_argument("--scheduler", default=None, help="default: the daemon chooses")
    parser.add_argument(
        "--adapter", default=None, help="the simulated adapter (default: the simulator's, bcm2835)"
    )
    parser.add_argument("--ioctl-us", type=float, default=None, help="the simulated cost of one ioctl (us)")
    parser.add_argument("--clock-hz", type=float, default=None, help="the simulated wire's real clock (Hz)")
    parser.add_argument(
        "--fifo",
        type=int,
        default=0,
        help="run the daemon SCHED_FIFO at this priority (0: not; the systemd unit sets 50)",
    )
    args = parser.parse_args()
    options = "&".join(
        f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}"
        for k, v in (("adapter", args.adapter), ("ioctl_us", args.ioctl_us), ("clock_hz", args.clock_hz))
        if v is not None
    )
    bus = "sim" + (f"?{options}" if options else "")
    load0 = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        lines = {"rate_hz": f"{args.rate:g}", "bus": f'"{bus}"'}
        if args.scheduler:
            lines["scheduler"] = f'"{args.scheduler}"'
        config = packaged_config(Path(tmp) / "ftsensord.toml", **lines)
        proc, notify = start_daemon(config, Path(tmp), fifo=args.fifo)
        folder = Path(tmp) / "ftsensord"
        control = ControlClient(f"ipc://{folder / 'control'}", timeout_s=5)
        try:
            control.status()
            with Subscriber(f"ipc://{folder / 'wrench'}", ["wrench/sensor1"]) as sub:
                first = sub.receive(timeout_s=5)
                cpu0, wall0 = cpu_seconds(proc.pid), time.monotonic()
                status0 = control.status()
                last = first
                end = time.monotonic() + args.seconds
                while time.monotonic() < end:
                    sample = sub.receive(timeout_s=5)
                    if sample is None:
                        break
                    last = sample
                cpu1, wall1 = cpu_seconds(proc.pid), time.monotonic()
                status1 = control.status()
                gaps = sub.gaps.get("wrench/sensor1", 0)
                received = sub.received - 1
        finally:
            stop(proc, notify)
    achieved = (last.seq - first.seq) / (last.t_mono - first.t_mono)
    error = (achieved - args.rate) / args.rate
    policy = f"SCHED_FIFO {args.fifo}" if args.fifo else "the default policy (SCHED_OTHER)"
    print(
        f"configured {args.rate:g} Hz, scheduler {status1['scheduler']}, 16 chips, bus {bus!r} in real time, "
        f"daemon at {policy} (load {load0:.2f} at start, {os.getloadavg()[0]:.2f} at end)"
    )
    print(
        f"bound: {status1['bound']}; the bus: adapter {status1.get('adapter')}, ioctl {status1.get('ioctl_us')} us, "
        f"clock {status1.get('clock_hz')} Hz"
    )
    print(f"schedule: {status1['schedule']}")
    print(
        f"over {last.t_mono - first.t_mono:.1f} s: {received} samples received, achieved {achieved:.3f} Hz "
        f"({error * 100:+.3f} % of configured), {gaps} sequence gaps"
    )
    print(
        f"daemon: missed cycles {status1['missed_cycles'] - status0['missed_cycles']}, late cycles "
        f"{status1['late_cycles'] - status0['late_cycles']} (started over a tenth of a period late); "
        f"jitter of the last 1000 cycles p50 {status1['jitter_us']['p50']:.0f} us, "
        f"p99 {status1['jitter_us']['p99']:.0f} us, max {status1['jitter_us']['max']:.0f} us"
    )
    cycle = status1["cycle_us"]
    n_last = min(1000, status1["cycles"])
    print(
        f"cycle (read, estimate, publish) of the last {n_last}: p50 {cycle['p50']:.0f} us, p99 {cycle['p99']:.0f} us, "
        f"max {cycle['max']:.0f} us of a {status1['period_us']:.0f} us period: "
        f"{(1 - cycle['p99'] / status1['period_us']) * 100:.0f} % of the period spare at p99"
    )
    print(f"daemon CPU: {(cpu1 - cpu0) / (wall1 - wall0) * 100:.1f} % of one core (bus simulation included)")
    return 0 if abs(error) <= 0.01 else 1


if __name__ == "__main__":
    raise SystemExit(main())
