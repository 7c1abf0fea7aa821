"""Sample-to-subscriber latency with many subscribers over ipc.

Starts `ftsensord run` with the default configuration (16 simulated chips in real time,
100 Hz, the default scheduler) in a subprocess, and ``--subscribers`` subscribers to
``wrench/sensor1`` spread over ``--processes`` processes (a subscriber in each its own
ZeroMQ socket, as separate client programs would have). Each receipt's delay is the
subscriber's CLOCK_MONOTONIC at receipt minus the sample's ``t_mono`` (the daemon's
CLOCK_MONOTONIC when the chips had been read): one clock, no synchronisation needed.
Reports p50, p99 and max over every receipt, the count, and the host's load.

    python benchmarks/latency.py --subscribers 50 --seconds 30
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import zmq

from ftsensord.service import wire
from ftsensord.service.config import builtin_path

SETTLE_S = 1.0  # connections made and the first samples through before counting


def listen(endpoint: str, n: int, seconds: float, out: mp.Queue) -> None:
    """``n`` subscribers in one process; put the delays (s) of every receipt after the settle."""
    ctx = zmq.Context()
    poller = zmq.Poller()
    socks = []
    for _ in range(n):
        s = ctx.socket(zmq.SUB)
        s.setsockopt(zmq.LINGER, 0)
        s.setsockopt(zmq.SUBSCRIBE, b"wrench/sensor1\0")
        s.connect(endpoint)
        poller.register(s, zmq.POLLIN)
        socks.append(s)
    delays: list[float] = []
    start = time.monotonic()
    end = start + SETTLE_S + seconds
    while time.monotonic() < end:
        received: list[tuple[float, bytes]] = []
        for sock, _ in poller.poll(timeout=100):
            while True:
                try:
                    frame = sock.recv(zmq.NOBLOCK)
                except zmq.Again:
                    break
                received.append((time.monotonic(), frame))
        # Decoded after every ready socket is read: the next socket's receipt is not
        # delayed by this one's decoding (the benchmark's own work, not the daemon's).
        delays += [t - wire.decode(frame).t_mono for t, frame in received if t - start >= SETTLE_S]
    for s in socks:
        s.close()
    ctx.term()
    out.put(delays)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--subscribers", type=int, default=50)
    parser.add_argument("--processes", type=int, default=5, help="subscriber processes (default 5)")
    parser.add_argument("--seconds", type=float, default=30.0)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        config = Path(tmp) / "ftsensord.toml"
        config.write_text(builtin_path("sim.toml").read_text().replace("builtin:", str(builtin_path("")) + "/"))
        env = {**os.environ, "XDG_RUNTIME_DIR": tmp}
        env.pop("RUNTIME_DIRECTORY", None)
        proc = subprocess.Popen([sys.executable, "-m", "ftsensord", "run", "--config", str(config)], env=env,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        endpoint_path = Path(tmp) / "ftsensord" / "wrench"
        try:
            for _ in range(100):
                if endpoint_path.exists():
                    break
                time.sleep(0.1)
            time.sleep(0.5)
            queue: mp.Queue = mp.Queue()
            per = [args.subscribers // args.processes + (i < args.subscribers % args.processes)
                   for i in range(args.processes)]
            workers = [mp.Process(target=listen, args=(f"ipc://{endpoint_path}", n, args.seconds, queue))
                       for n in per if n]
            load0 = os.getloadavg()[0]
            for w in workers:
                w.start()
            delays = [d for _ in workers for d in queue.get(timeout=args.seconds + 60)]
            for w in workers:
                w.join()
        finally:
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=10)
    d = np.array(delays) * 1e6
    expected = args.subscribers * args.seconds * 100
    print(f"{args.subscribers} subscribers in {len(workers)} processes to wrench/sensor1 over ipc, the daemon at "
          f"100 Hz, {args.seconds:g} s (load {load0:.2f} at start, {os.getloadavg()[0]:.2f} at end)")
    print(f"{len(d)} receipts (of about {expected:.0f}): sample t_mono to receipt p50 {np.percentile(d, 50):.0f} us, "
          f"p99 {np.percentile(d, 99):.0f} us, max {d.max():.0f} us")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
