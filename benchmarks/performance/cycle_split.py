"""Where a 100 Hz cycle of the daemon goes, on the simulated bus in real time.

Runs the daemon (`Daemon.cycle` and its control service between cycles, the default
configuration: 16 chips, burst, the simulated Pi 4 adapter) in this process on the
real-time simulated bus, and splits every cycle into:

- ``transfers``: wall time inside ``i2c_rdwr`` (the simulated wire and ioctl time, plus
  whatever the simulator's own Python spent beyond it: ``spill``);
- ``host``: the rest of the cycle, the daemon's own work (reader's decoding and health,
  estimate, publish), with its thread CPU time beside it (``host_cpu``);
- ``sim_cpu``: the thread CPU spent inside ``i2c_rdwr`` (the emulated chips' physics and
  the clock's spin), which a board's adapter does not cost the host.

``spill`` is per transfer how long the simulator's CPU ran past the transfer's wire end
(it then lengthens the transfer, which a board's would not): it should be 0. The bound
counts transfers only; a cycle is about ``bound + host``. The split's own clock reads
(two ``thread_time`` and three ``monotonic`` a transfer, about 2 us) are in its figures.
Run:

    python -m benchmarks.performance.cycle_split [--cycles 1000] [--bus 'sim?adapter=bcm2835&ioctl_us=80'] [--fifo 50]

``--fifo PRIO`` runs this process SCHED_FIFO (as the systemd unit runs the daemon; needs
the privilege to). ``--virtual-clock`` runs the same cycles on the simulated bus's virtual
clock instead: no sleep, no wake-up, the same code and physics, so ``host_cpu`` there is
the code's own cost and the difference to a real-time run is what waking up costs.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import zmq

from ftsensord.config.file import load_config
from ftsensord.daemon.daemon import Daemon
from ftsensord.daemon.run import make_sockets, open_configured_bus
from ftsensord.sim import MonotonicClock, VirtualClock
from ftsensord.testing.harness import packaged_config

SETTLE_CYCLES = 20  # chips started, plans built and caches warm before counting


class Split:
    """Wraps a simulated bus's ``i2c_rdwr`` and its clock's ``wait_until`` to add up
    the time and CPU inside transfers and the simulator's spill past a transfer's end."""

    def __init__(self, bus: Any):
        self.bus, self.rdwr, self.wait, self.now = bus, bus.i2c_rdwr, bus.clock.wait_until, bus.clock.now
        self.wall = self.cpu = 0.0
        self.spills: list[float] = []
        self.inside = False
        bus.i2c_rdwr, bus.clock.wait_until = self.i2c_rdwr, self.wait_until

    def i2c_rdwr(self, *msgs: Any) -> None:
        t0, c0 = self.now(), time.thread_time()
        self.inside = True
        try:
            self.rdwr(*msgs)
        finally:
            self.inside = False
            self.wall += self.now() - t0
            self.cpu += time.thread_time() - c0

    def wait_until(self, t: float) -> None:
        if self.inside:  # the transfer's end: how far past it the simulator's CPU already is
            self.spills.append(max(0.0, self.now() - t))
        self.wait(t)


def percentiles(x: np.ndarray) -> str:
    return f"p50 {np.percentile(x, 50):6.0f}  p99 {np.percentile(x, 99):6.0f}  max {x.max():6.0f}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cycles", type=int, default=1000)
    parser.add_argument("--bus", default="sim?adapter=bcm2835&ioctl_us=80")
    parser.add_argument("--fifo", type=int, default=0, help="run SCHED_FIFO at this priority (0: not)")
    parser.add_argument(
        "--virtual-clock", action="store_true", help="the simulated bus's virtual clock: no sleeps"
    )
    args = parser.parse_args()
    if args.fifo:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.fifo))
    load0 = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        os.environ["XDG_RUNTIME_DIR"] = tmp
        os.environ.pop("RUNTIME_DIRECTORY", None)
        config = load_config(packaged_config(Path(tmp) / "ftsensord.toml", bus=f'"{args.bus}"'))
        clock = VirtualClock() if args.virtual_clock else MonotonicClock()
        bus = open_configured_bus(config, clock)
        context = zmq.Context()
        publisher, control, _ = make_sockets(context, config)
        daemon = Daemon(config, bus, publisher, control, clock=clock.now)
        daemon.start()
        split = Split(bus)
        rows = []
        deadline = clock.now()
        for k in range(SETTLE_CYCLES + args.cycles):
            if k == SETTLE_CYCLES:
                split.spills.clear()
            w0, c0, xw0, xc0 = clock.now(), time.thread_time(), split.wall, split.cpu
            daemon.cycle(max(0.0, w0 - deadline))
            w1, c1 = clock.now(), time.thread_time()
            if k >= SETTLE_CYCLES:
                rows.append((w1 - w0, split.wall - xw0, split.cpu - xc0, (c1 - c0) - (split.cpu - xc0)))
            deadline += daemon.period_s
            if args.virtual_clock:
                clock.wait_until(deadline)  # type: ignore[union-attr]
            else:
                daemon.serve_until(deadline)
        daemon.reader.stop()
        publisher.close()
        control.close()
        context.term()
        bound_us = config.bound(daemon.board_timing).cycle_s * 1e6
    a = np.array(rows) * 1e6
    spills = np.array(split.spills) * 1e6
    policy = f"SCHED_FIFO {args.fifo}" if args.fifo else "the default policy"
    policy += ", virtual clock" if args.virtual_clock else ""
    print(
        f"{args.cycles} cycles at {config.rate_hz:g} Hz, {config.scheduler}, bus {args.bus!r}, {policy} "
        f"(load {load0:.2f} at start, {os.getloadavg()[0]:.2f} at end); us a cycle:"
    )
    print(f"  cycle       {percentiles(a[:, 0])}   (bound {bound_us:.0f})")
    print(f"  transfers   {percentiles(a[:, 1])}")
    print(f"  host        {percentiles(a[:, 0] - a[:, 1])}   (cycle - transfers)")
    print(f"  host_cpu    {percentiles(a[:, 3])}   (thread CPU outside transfers)")
    print(f"  sim_cpu     {percentiles(a[:, 2])}   (thread CPU inside transfers: physics, spin)")
    print(
        f"  spill       {percentiles(spills)}   per transfer ({len(spills)}; "
        f"{np.count_nonzero(spills)} past their end)"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
