"""Sample-to-subscriber latency with many subscribers over ipc.

Starts `ftsensord run` with the default configuration (16 simulated chips in real time,
100 Hz, the scheduler the daemon chooses) in a subprocess, and ``--subscribers`` subscribers to
``wrench/sensor1`` spread over ``--processes`` processes (a subscriber in each its own
ZeroMQ socket, as separate client programs would have). Each receipt's delay is the
subscriber's CLOCK_MONOTONIC at receipt minus the sample's ``t_mono`` (the daemon's
CLOCK_MONOTONIC when the chips had been read): one clock, no synchronisation needed.
Reports p50, p99 and max over every receipt, the count, and the host's load, and from the
daemon's status the part that is the daemon's own: from ``t_mono`` to the return of its
first stream's send (``publish_us``); the rest is ZeroMQ's fan-out and the subscribers'
own scheduling.

``--kind python`` (the default) runs the subscribers as Python processes (pyzmq);
``--kind c`` as C programs on clients/c/ftsensord.h (benchmarks/performance/latency_sub.c, built as
clients/c/build.py builds the example, against the libzmq the pyzmq wheel ships when no
system one is found): what the haptic loops that use the daemon are. ``--fifo PRIO`` runs
the daemon SCHED_FIFO as the systemd unit does.

    python -m benchmarks.performance.latency --subscribers 50 --seconds 30 [--kind c] [--processes 5] \
        [--fifo 50] [--cpus 1]
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import resource
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np
import zmq

from benchmarks.common import load_c_build
from ftsensord.client import ControlClient
from ftsensord.protocol import wire
from ftsensord.testing.harness import cpu_seconds, packaged_config, start_daemon, stop

SETTLE_S = 1.0  # connections made and the first samples through before counting


def children_cpu_s() -> float:
    """User and system CPU (s) of the children waited for so far (the subscribers, once joined)."""
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def build_c(folder: Path) -> tuple[Path, str]:
    """benchmarks/performance/latency_sub.c built into ``folder`` (clients/c/build.py's libzmq);
    the program and the libzmq used."""
    build = load_c_build()
    libzmq = build.find_libzmq()
    program = folder / "latency_sub"
    build.build([Path(__file__).with_name("latency_sub.c")], program, "c", libzmq)
    return program, libzmq.origin


def listen(endpoint: str, n: int, seconds: float, out: mp.Queue) -> None:
    """``n`` subscribers in one process; put (seq, delay in s) of every receipt after the settle."""
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
    delays: list[tuple[int, float]] = []
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
        samples = [(t, wire.decode(frame)) for t, frame in received if t - start >= SETTLE_S]
        delays += [(s.seq, t - s.t_mono) for t, s in samples]
    for s in socks:
        s.close()
    ctx.term()
    out.put(delays)


def listen_c(
    program: Path, endpoint: str, per: list[int], seconds: float, shared: bool = False
) -> tuple[list[tuple[int, float]], list[str]]:
    """The C subscribers, ``per[i]`` in process i (``shared``: on one context each process);
    (seq, delay in s) of every receipt after the settle."""
    procs = [
        subprocess.Popen(
            [
                str(program),
                endpoint,
                "wrench/sensor1",
                str(n),
                str(SETTLE_S),
                str(seconds),
                *(["shared"] if shared else []),
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for n in per
    ]
    delays: list[tuple[int, float]] = []
    summaries = []
    for p in procs:
        out, err = p.communicate(timeout=seconds + 60)
        if p.returncode != 0:
            raise RuntimeError(f"{program.name} failed ({p.returncode}): {err.strip()}")
        delays += [(int(seq), int(ns) * 1e-9) for seq, ns in (line.split() for line in out.splitlines())]
        summaries.append(err.strip())
    return delays, summaries


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--subscribers", type=int, default=50)
    parser.add_argument("--processes", type=int, default=5, help="subscriber processes (default 5)")
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument(
        "--kind",
        choices=("python", "c"),
        default="python",
        help="the subscribers: Python (pyzmq) or C programs on clients/c/ftsensord.h",
    )
    parser.add_argument(
        "--fifo",
        type=int,
        default=0,
        help="run the daemon SCHED_FIFO at this priority (0: not; the systemd unit sets 50)",
    )
    parser.add_argument(
        "--shared-context",
        action="store_true",
        help="C: a process's subscribers share one libzmq context (one I/O thread), "
        "instead of one each as separate programs have",
    )
    parser.add_argument(
        "--cpus",
        type=int,
        default=0,
        help="run the daemon and the subscribers on this many cores (0: all), to see how the "
        "fan-out scales with cores",
    )
    args = parser.parse_args()
    if args.cpus:  # inherited by the daemon and every subscriber process
        os.sched_setaffinity(0, set(sorted(os.sched_getaffinity(0))[: args.cpus]))
    with tempfile.TemporaryDirectory() as tmp:
        config = packaged_config(Path(tmp) / "ftsensord.toml")
        program, libzmq = build_c(Path(tmp)) if args.kind == "c" else (None, f"pyzmq {zmq.__version__}")
        proc, notify = start_daemon(config, Path(tmp), fifo=args.fifo)
        endpoint_path = Path(tmp) / "ftsensord" / "wrench"
        control = ControlClient(f"ipc://{Path(tmp) / 'ftsensord' / 'control'}", timeout_s=5)
        try:
            time.sleep(0.5)
            per = [
                n
                for n in (
                    args.subscribers // args.processes + (i < args.subscribers % args.processes)
                    for i in range(args.processes)
                )
                if n
            ]
            load0 = os.getloadavg()[0]
            children0, daemon0, wall0 = children_cpu_s(), cpu_seconds(proc.pid), time.monotonic()
            if program is not None:
                delays, summaries = listen_c(
                    program, f"ipc://{endpoint_path}", per, args.seconds, args.shared_context
                )
            else:
                queue: mp.Queue = mp.Queue()
                workers = [
                    mp.Process(target=listen, args=(f"ipc://{endpoint_path}", n, args.seconds, queue))
                    for n in per
                ]
                for w in workers:
                    w.start()
                delays = [d for _ in workers for d in queue.get(timeout=args.seconds + 60)]
                for w in workers:
                    w.join()
                summaries = []
            children1, daemon1, wall1 = children_cpu_s(), cpu_seconds(proc.pid), time.monotonic()
            status = control.status()
        finally:
            stop(proc, notify)
    seqs = np.array([q for q, _ in delays])
    d = np.array([x for _, x in delays]) * 1e6
    expected = args.subscribers * args.seconds * 100
    policy = f"SCHED_FIFO {args.fifo}" if args.fifo else "the default policy"
    contexts = " sharing a context a process" if args.kind == "c" and args.shared_context else ""
    print(
        f"{args.subscribers} {args.kind} subscribers{contexts} ({libzmq}) in {len(per)} processes "
        "to wrench/sensor1 over ipc, "
        f"the daemon at 100 Hz at {policy}, {args.seconds:g} s, {len(os.sched_getaffinity(0))} cores "
        f"(load {load0:.2f} at start, "
        f"{os.getloadavg()[0]:.2f} at end)"
    )
    print(
        f"{len(d)} receipts (of about {expected:.0f}): sample t_mono to receipt p50 {np.percentile(d, 50):.0f} us, "
        f"p99 {np.percentile(d, 99):.0f} us, max {d.max():.0f} us"
    )
    publish = status.get("publish_us")
    if publish:
        print(
            f"the daemon's part (status publish_us, last {min(1000, status['cycles'])} cycles): t_mono to its "
            f"first stream's send returned p50 {publish['p50']:.0f} us, p99 {publish['p99']:.0f} us, "
            f"max {publish['max']:.0f} us; missed cycles {status['missed_cycles']}"
        )
    # Per sample: its first and its last receipt among the subscribers (samples every one got).
    order = np.argsort(seqs, kind="stable")
    starts = np.flatnonzero(np.diff(seqs[order], prepend=-1))
    counts = np.diff(np.append(starts, len(order)))
    whole = counts == args.subscribers
    first = np.minimum.reduceat(d[order], starts)[whole]
    last = np.maximum.reduceat(d[order], starts)[whole]
    if len(first):
        print(
            f"per sample ({len(first)} samples all {args.subscribers} received): first receipt p50 "
            f"{np.percentile(first, 50):.0f} us, p99 {np.percentile(first, 99):.0f} us; last receipt p50 "
            f"{np.percentile(last, 50):.0f} us, p99 {np.percentile(last, 99):.0f} us"
        )
    print(
        f"CPU: the subscribers {(children1 - children0) / max(1, len(d)) * 1e6:.1f} us a receipt "
        f"({(children1 - children0) / (wall1 - wall0) * 100:.0f} % of a core), the daemon (ZeroMQ's I/O thread and the "
        f"bus simulation included) {(daemon1 - daemon0) / (wall1 - wall0) * 100:.0f} % of a core"
    )
    for line in summaries:
        print(f"  {line}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
