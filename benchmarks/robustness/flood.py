"""Control traffic against the real daemon: does the loop come first?

    python -m benchmarks.robustness.flood status --seconds 20    # four clients flooding `status`
    python -m benchmarks.robustness.flood hostile --count 20000  # hostile messages, oversized numbers, nesting
    python -m benchmarks.robustness.flood burn --seconds 20      # control: four processes only spinning the CPU
    python -m benchmarks.robustness.flood reload --seconds 20 --scheduler overlapped   # four clients flooding `reload`

Runs `ftsensord run` (the packaged simulated configuration: 16 chips, 100 Hz, real
400 kHz wire time) with NOTIFY_SOCKET bound here and WATCHDOG_USEC=5 s (the unit's
WatchdogSec), subscribes to wrench/sensor1 and reports the stream's rate, its sequence
jumps (skipped cycles), the watchdog pings (WATCHDOG=1 datagrams) and the largest gap
between them, and what the clients got. Each client is its own process (a DEALER
keeping 20 requests in flight, as fast as replies come).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import zmq

from ftsensord.client import ControlClient
from ftsensord.daemon.control import MAX_REQUEST
from ftsensord.protocol import wire
from ftsensord.testing.harness import packaged_config, start_daemon, stop

IN_FLIGHT = 20
WATCHDOG_USEC = 5_000_000
COMMANDS = ["status", "tare", "reload", "set", "launch", "", "STATUS", "\u00e9\u00e8", "x" * 300]


def hostile(rng: np.random.Generator) -> bytes:
    """One hostile request (under the size limit): garbage, nesting, numbers over Python's
    int limit, valid JSON of the wrong shape, junk arguments, cut-short text."""
    kind = int(rng.integers(0, 9))
    if kind == 0:
        return rng.bytes(int(rng.integers(0, 200)))
    if kind == 1:
        return b"[" * int(rng.integers(1, 50_000))
    if kind == 2:
        digits = "9" * int(rng.integers(4_301, 60_000))  # Python's int() refuses over 4300
        return ('{"cmd":"status","n":' + digits + "}").encode()
    if kind == 3:
        depth = int(rng.integers(9, 10_000))  # 6 bytes a level: under the 64 KiB limit
        return ('{"cmd":"status","x":' + '{"a":' * depth + "1" + "}" * depth + "}").encode()
    if kind == 4:  # a long float the rate's range refuses: a valid one (1.555...) would really set the
        # rate, a change that is a controller's to make (it slowed the loop to 1.56 Hz), not a flood's
        return ('{"cmd":"set","rate_hz":0.' + "0" * int(rng.integers(101, 30_000)) + "1}").encode()
    junk = [None, True, -1, 1e308, "x", [], {}, [1, [2]], {"a": {"b": 1}}, 10**30, float("nan")]
    request: dict = {"cmd": COMMANDS[int(rng.integers(len(COMMANDS)))]}
    for _ in range(int(rng.integers(1, 4))):  # at least one argument: no real reload or tare
        key = ["samples", "sensor", "rate_hz", "averaging", "lowpass_hz", "path", "cmd"][int(rng.integers(7))]
        request[key] = junk[int(rng.integers(len(junk)))]
    if kind == 5:
        request["cmd"] = junk[int(rng.integers(len(junk)))]
    text = json.dumps(request)
    if kind == 6:
        text = text[: int(rng.integers(0, len(text)))]
    return text.encode("utf-8", "surrogatepass")


def client(
    endpoint: str, seconds: float, seed: int, count: int, mode: str, out: mp.Queue, nice: int = 0
) -> None:
    """Keep IN_FLIGHT requests in flight until ``seconds`` pass or ``count`` are sent
    (``burn``: send nothing, spin the CPU as long: what the clients cost the machine).
    ``nice``: the clients' niceness (the daemon's priority over its clients is the OS's to give)."""
    os.nice(nice)
    if mode == "burn":
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            pass
        out.put({"sent": 0, "replies": 0, "errors": 0})
        return
    ctx = zmq.Context()
    sock = ctx.socket(zmq.DEALER)
    sock.setsockopt(zmq.LINGER, 0)
    sock.connect(endpoint)
    rng = np.random.default_rng(seed)
    sent = replies = errors = 0
    end = time.monotonic() + seconds
    while time.monotonic() < end and (count == 0 or replies < count):
        while sent - replies < IN_FLIGHT and (count == 0 or sent < count):
            payload = b'{"cmd":"%s"}' % mode.encode() if mode in ("status", "reload") else hostile(rng)
            assert len(payload) <= MAX_REQUEST
            sock.send_multipart([b"", payload])
            sent += 1
        if sock.poll(1000):
            reply = json.loads(sock.recv_multipart()[-1])
            replies += 1
            errors += not reply["ok"]
    out.put({"sent": sent, "replies": replies, "errors": errors})
    sock.close()
    ctx.term()


def cpu_s(pid: int) -> float:
    """CPU seconds (user + system) a process has used so far."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def run(
    mode: str,
    seconds: float,
    clients: int,
    count: int,
    nice: int = 0,
    fifo: int = 0,
    daemon_nice: int = 0,
    scheduler: str = "",
) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        tmp_path = Path(tmp)
        config = packaged_config(
            tmp_path / "ftsensord.toml", **({"scheduler": f'"{scheduler}"'} if scheduler else {})
        )
        # The daemon's priority as the unit's CPUSchedulingPolicy=fifo (fifo) or Nice= (daemon_nice) would set it.
        proc, notify = start_daemon(
            config, tmp_path, fifo=fifo, nice=daemon_nice, env={"WATCHDOG_USEC": str(WATCHDOG_USEC)}
        )
        notify.setblocking(False)
        folder = tmp_path / "ftsensord"
        ctx = zmq.Context()
        sub = ctx.socket(zmq.SUB)
        sub.setsockopt(zmq.RCVHWM, 0)
        sub.setsockopt(zmq.SUBSCRIBE, b"wrench/sensor1\0")
        sub.connect(f"ipc://{folder / 'wrench'}")
        time.sleep(1.0)  # settle: the subscription reaches the daemon
        pings: list[float] = []
        seqs: list[int] = []

        def drain(until: float) -> None:
            while time.monotonic() < until:
                if sub.poll(20):
                    seqs.append(wire.decode(sub.recv()).seq)
                while True:
                    try:
                        if notify.recv(4096).startswith(b"WATCHDOG=1"):
                            pings.append(time.monotonic())
                    except BlockingIOError:
                        break

        drain(time.monotonic() + 1.0)
        seqs.clear()
        pings.clear()
        out: mp.Queue = mp.Queue()
        per_client = count // clients if count else 0
        endpoint = f"ipc://{folder / 'control'}"
        procs = [
            mp.Process(target=client, args=(endpoint, seconds, i, per_client, mode, out, nice))
            for i in range(clients)
        ]
        t0, daemon_cpu0, children0, load0 = time.monotonic(), cpu_s(proc.pid), os.times(), os.getloadavg()[0]
        for p in procs:
            p.start()
        while time.monotonic() < t0 + seconds and (not procs or any(p.is_alive() for p in procs)):
            drain(min(t0 + seconds, time.monotonic() + 0.5))  # until the clients are done
        results = [out.get(timeout=60) for _ in procs]
        for p in procs:
            p.join()
        elapsed = time.monotonic() - t0
        alive = proc.poll() is None
        # The loop's own view of its last 1000 cycles (10 s, the end of the flood): how long a
        # cycle took and how late it started, p50, p99, max in us.
        loop = ControlClient(endpoint, timeout_s=5).status() if alive else {}
        daemon_cpu = cpu_s(proc.pid) - daemon_cpu0 if alive else float("nan")
        children = os.times()  # the clients, joined: what they took from the daemon's two cores
        clients_cpu = (
            children.children_user
            + children.children_system
            - children0.children_user
            - children0.children_system
        )
        load1 = os.getloadavg()[0]
        exit_code = stop(proc, notify)
        sub.close(linger=0)
        ctx.term()
    jumps = int(sum(np.diff(seqs) - 1)) if len(seqs) > 1 else 0
    gaps = np.diff([t0, *pings, t0 + elapsed])
    return {
        "mode": mode,
        "clients": clients,
        "client_nice": nice,
        "daemon_fifo": fifo,
        "daemon_nice": daemon_nice,
        "seconds": round(elapsed, 2),
        "alive": alive,
        "exit": exit_code,
        "load_average_1min": [round(load0, 2), round(load1, 2)],
        "cpu_share_daemon": round(daemon_cpu / elapsed, 3),
        "cpu_share_clients": round(clients_cpu / elapsed, 3),
        "samples": len(seqs),
        "rate_hz": round(len(seqs) / elapsed, 2),
        "rate_share": round(
            (seqs[-1] - seqs[0] + 1 and len(seqs) / (seqs[-1] - seqs[0] + 1)) if seqs else 0, 4
        ),
        "skipped_cycles": jumps,
        "watchdog_pings": len(pings),
        "max_ping_gap_s": round(float(gaps.max()), 3),
        "watchdog_s": WATCHDOG_USEC / 1e6,
        **{k: {q: round(v) for q, v in loop[k].items()} for k in ("cycle_us", "jitter_us") if k in loop},
        "sent": sum(r["sent"] for r in results),
        "replies": sum(r["replies"] for r in results),
        "errors": sum(r["errors"] for r in results),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("mode", choices=("status", "hostile", "burn", "reload"))
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--clients", type=int, default=4)
    parser.add_argument("--count", type=int, default=0, help="messages in all (0: as many as fit the time)")
    parser.add_argument("--nice", type=int, default=0, help="the clients' niceness (0: the daemon's)")
    parser.add_argument(
        "--fifo",
        type=int,
        default=0,
        help="run the daemon SCHED_FIFO at this priority (0: not; the unit sets 50)",
    )
    parser.add_argument("--daemon-nice", type=int, default=0, help="run the daemon at this niceness (0: not)")
    parser.add_argument(
        "--scheduler", default="", help="the daemon's scheduler (default: the packaged one's)"
    )
    args = parser.parse_args()
    print(
        json.dumps(
            run(
                args.mode,
                args.seconds,
                args.clients,
                args.count,
                args.nice,
                args.fifo,
                args.daemon_nice,
                args.scheduler,
            ),
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
