"""Hostile neighbours against the real daemon under its own unit's restrictions
(benchmarks/robustness/unit_sandbox.py: system call filter, LimitNOFILE, MemoryMax as a memory cgroup
where this host lets us make one, the FIFO policy where allowed).

    python -m benchmarks.robustness.hostile descriptors --connections 3000   # held on control and wrench each
    python -m benchmarks.robustness.hostile unread --clients 127 --requests 1000  # clients that never read
    python -m benchmarks.robustness.hostile stalled --clients 127 --seconds 20   # subscribers that never read
    python -m benchmarks.robustness.hostile calibration --runs 20   # a huge calibration file, one at the limit
    python -m benchmarks.robustness.hostile early-stop --delays 0.02,0.1,0.3,0.5,0.7,0.9   # SIGTERM while starting
    python -m benchmarks.robustness.hostile first-status --runs 5   # the first `status`'s cost, fresh processes

`descriptors` opens plain AF_UNIX connections to the control and wrench sockets as fast
as it can and holds them (libzmq accepts them before any handshake), then asks `status`
over a connection of its own: alive or not, the daemon's descriptors at their peak, the
connections kept and refused. `unread` starts DEALER clients that send `status` requests
and never read a reply, and reports the daemon's RSS before, at the peak and after the
clients left, and the replies dropped. `stalled` connects SUB clients to every stream that
never read (their own queues and socket buffers as small as they go, so the daemon's queue
fills), beside one recorder that reads: the daemon's RSS before, with them and after, and
the recorder's sequence gaps against the cycles the loop skipped. `calibration` (in this process, no daemon) times
`Calibration.load` refusing a 200 MB file, and reading one padded to the size limit with
numbers (the slowest JSON to parse). `early-stop` sends SIGTERM to `ftsensord run` that
long after starting it and reports its exit status and the files it left. `first-status`
times the first and second `status` of a daemon in a fresh process (on a virtual clock,
packaged configuration): a lazy import in the first is paid within a cycle. Each prints
one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import zmq

from benchmarks.common import ROOT
from benchmarks.robustness.unit_sandbox import MemoryGroup, UnitRestrictions, seccomp_available
from ftsensord.client import ControlClient
from ftsensord.testing.harness import packaged_config, start_daemon, stop

UNIT = ROOT / "systemd" / "ftsensord.service"


def sandboxed(
    config: Path, folder: Path, unit: UnitRestrictions, memory: MemoryGroup | None = None
) -> tuple[subprocess.Popen, socket.socket]:
    """`ftsensord run` under ``unit`` (the filter only where seccomp is available; in
    ``memory``, a group made for its MemoryMax=, where one could be made), its output in
    ``folder``/daemon.log."""
    if not seccomp_available():
        unit.filters = []
    with open(folder / "daemon.log", "w") as log:
        return start_daemon(
            config,
            folder,
            args=unit.run_args,
            preexec_fn=unit.preexec(memory=memory),
            stdout=log,
            stderr=subprocess.STDOUT,
        )


def memory_kib(pid: int) -> dict[str, int]:
    """VmRSS and VmHWM (peak) of ``pid``, KiB."""
    out = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            out[key] = int(value.split()[0])
    return out


def descriptor_count(pid: int) -> int:
    return len(os.listdir(f"/proc/{pid}/fd"))


def hold_connections(path: Path, count: int, pid: int) -> tuple[list[socket.socket], int, int]:
    """``count`` connections to the ipc socket at ``path``, held open; with those the
    kernel refused (the listener gone or its backlog full past the timeout), and the most
    descriptors process ``pid`` (the daemon) had, counted every 100 connections."""
    held, refused, most = [], 0, 0
    for i in range(count):
        if i % 100 == 0 and os.path.exists(f"/proc/{pid}"):
            most = max(most, descriptor_count(pid))
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        # A blocking connect waits (up to SO_SNDTIMEO) while the listener's backlog is full;
        # settimeout() would make the socket non-blocking, and the kernel would then refuse
        # at once with EAGAIN whenever the daemon is slower to accept than this loop connects.
        s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDTIMEO, struct.pack("ll", 1, 0))
        try:
            s.connect(str(path))
            held.append(s)
        except OSError:
            s.close()
            refused += 1
    return held, refused, most


def descriptors(folder: Path, proc: subprocess.Popen, connections: int) -> dict[str, Any]:
    """``connections`` held on each of control and wrench, then `status` asked."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))  # this side must not run out first
    before = descriptor_count(proc.pid)
    held: list[socket.socket] = []
    try:
        t0 = time.perf_counter()
        refused = most = 0
        for name in ("control", "wrench"):
            got, r, m = hold_connections(folder / name, connections, proc.pid)
            held += got
            refused, most = refused + r, max(most, m)
        seconds = time.perf_counter() - t0
        # The kept ones that never handshake are closed after the daemon's HANDSHAKE_MS (1 s).
        time.sleep(1.5)
        alive = proc.poll() is None
        out: dict[str, Any] = {
            "connections_each": connections,
            "connect_seconds": round(seconds, 3),
            "refused_by_kernel": refused,
            "alive": alive,
            "exit": proc.poll(),
            "daemon_fds_before": before,
            "daemon_fds_most": most,
        }
        if alive:
            out["daemon_fds_held"] = descriptor_count(proc.pid)
            closed = sum(1 for s in held if _peer_closed(s))
            out["closed_by_daemon"] = closed
            status = ControlClient(f"ipc://{folder / 'control'}", timeout_s=10).status()
            out["status_connections"] = status.get("connections")
            out["cycles"] = status["cycles"]
        return out
    finally:
        for s in held:
            s.close()
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))


def _peer_closed(s: socket.socket) -> bool:
    """The daemon closed it (libzmq's greeting read first, then the end of the stream)."""
    s.setblocking(False)
    try:
        while s.recv(4096):
            pass
        return True
    except BlockingIOError:
        return False
    except OSError:
        return True


def silent_clients(
    ctx: zmq.Context, kind: int, endpoint: str, count: int, options: dict[int, Any]
) -> list[zmq.Socket]:
    """``count`` sockets of ``kind`` connected to ``endpoint`` that read nothing: their own
    queue and socket buffer as small as they go, so what the daemon sends them waits in its
    own queues; ``options``: the kind's own (set after those)."""
    socks = []
    for _ in range(count):
        s = ctx.socket(kind)
        for option, value in {zmq.RCVHWM: 1, zmq.RCVBUF: 4096, zmq.LINGER: 0, **options}.items():
            s.setsockopt(option, value)
        s.connect(endpoint)
        socks.append(s)
    return socks


def leave(ctx: zmq.Context, socks: list[zmq.Socket], pid: int) -> int:
    """The clients gone (``socks`` closed, ``ctx`` ended): the daemon's RSS (KiB) once its I/O
    thread has freed their queues and `malloc_trim` (1 s after the last) given them back."""
    for s in socks:
        s.close()
    ctx.term()
    time.sleep(3.0)
    return memory_kib(pid)["VmRSS"]


def rss_figures(before: int, loaded: dict[str, int], after: int) -> dict[str, float]:
    """The daemon's RSS before the clients (KiB), with them (`memory_kib`) and after they left, in MiB."""
    return {
        "rss_before_mib": round(before / 1024, 1),
        "rss_loaded_mib": round(loaded["VmRSS"] / 1024, 1),
        "rss_peak_mib": round(loaded["VmHWM"] / 1024, 1),
        "rss_after_mib": round(after / 1024, 1),
    }


def unread(folder: Path, proc: subprocess.Popen, clients: int, requests: int) -> dict[str, Any]:
    """``clients`` DEALERs each sending ``requests`` `status` requests, reading nothing."""
    endpoint = f"ipc://{folder / 'control'}"
    control = ControlClient(endpoint, timeout_s=10)
    before = memory_kib(proc.pid)["VmRSS"]
    ctx = zmq.Context()
    socks = silent_clients(ctx, zmq.DEALER, endpoint, clients, {zmq.SNDHWM: requests})
    request = json.dumps({"cmd": "status"}).encode()
    for s in socks:
        for _ in range(requests):
            s.send_multipart([b"", request])
    # Until the daemon has answered or dropped everything (at most 32 a cycle): the count
    # of dropped replies steady for a second.
    deadline = time.monotonic() + max(30.0, 3 * clients * requests / 3200)
    status, dropped = control.status(), [-1, -2, -3]
    while time.monotonic() < deadline and not dropped[-1] == dropped[-3] > 0:
        time.sleep(0.5)
        status = control.status()
        dropped.append(status.get("replies_dropped", 0))
    loaded = memory_kib(proc.pid)
    after = leave(ctx, socks, proc.pid)
    return {
        "clients": clients,
        "requests_each": requests,
        **rss_figures(before, loaded, after),
        "replies_dropped": status.get("replies_dropped"),
        "alive": proc.poll() is None,
    }


def stalled(folder: Path, proc: subprocess.Popen, clients: int, seconds: float) -> dict[str, Any]:
    """``clients`` SUBs to every stream that never read, for ``seconds``, beside a recorder."""
    from ftsensord.client import Subscriber

    control = ControlClient(f"ipc://{folder / 'control'}", timeout_s=10)
    endpoint = f"ipc://{folder / 'wrench'}"
    before = memory_kib(proc.pid)["VmRSS"]
    ctx = zmq.Context()
    socks = silent_clients(ctx, zmq.SUB, endpoint, clients, {zmq.SUBSCRIBE: b""})
    missed0 = control.status()["missed_cycles"]
    received = 0
    with Subscriber(endpoint, context=ctx) as recorder:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            received += recorder.receive(timeout_s=1.0) is not None
        gaps = dict(recorder.gaps)
    status = control.status()
    loaded = memory_kib(proc.pid)
    after = leave(ctx, socks, proc.pid)
    return {
        "clients": clients,
        "seconds": seconds,
        **rss_figures(before, loaded, after),
        "recorder_received": received,
        "recorder_gaps": gaps,
        "missed_cycles": status["missed_cycles"] - missed0,
        "publish_connections_refused": status.get("connections", {}).get("publish", {}).get("refused"),
        "alive": proc.poll() is None,
    }


def calibration(runs: int) -> dict[str, Any]:
    """Median and largest time (ms) over ``runs`` of loading a 200 MB calibration file (refused
    by its size) and one of the packaged ones padded with numbers to MAX_CALIBRATION_BYTES."""
    from ftsensord.calibration.calfile import MAX_CALIBRATION_BYTES, Calibration
    from ftsensord.config.file import builtin_path
    from ftsensord.errors import ConfigError

    with tempfile.TemporaryDirectory() as tmp:
        huge = Path(tmp) / "huge.json"
        with huge.open("wb") as f:
            f.truncate(200 * 2**20)
        doc = json.loads(builtin_path("sim-sensor1.json").read_text())
        base = len(json.dumps(doc))
        doc["fit_report"]["padding"] = [0.123456789012345] * ((MAX_CALIBRATION_BYTES - base - 64) // 19)
        full = Path(tmp) / "full.json"
        full.write_text(json.dumps(doc))
        out: dict[str, Any] = {
            "runs": runs,
            "full_bytes": full.stat().st_size,
            "limit": MAX_CALIBRATION_BYTES,
        }
        raw = full.read_bytes()
        for name, work in (
            ("huge_refused_ms", lambda: Calibration.load(huge)),
            ("at_limit_ms", lambda: Calibration.load(full)),
            ("at_limit_json_ms", lambda: json.loads(raw)),
        ):  # one C call: the GIL held throughout
            times = []
            for _ in range(runs):
                t0 = time.perf_counter()
                try:
                    work()
                except ConfigError:
                    pass  # the huge one: refused, as it should be
                times.append((time.perf_counter() - t0) * 1e3)
            out[name] = {"median": round(sorted(times)[runs // 2], 3), "max": round(max(times), 3)}
        return out


def early_stop(delays: list[float]) -> dict[str, Any]:
    """SIGTERM ``delay`` s after starting `ftsensord run`: its exit status, the files left."""
    out = []
    for delay in delays:
        with tempfile.TemporaryDirectory() as tmp:
            folder = Path(tmp)
            config = packaged_config(folder / "ftsensord.toml")
            env = {**os.environ, "XDG_RUNTIME_DIR": str(folder)}
            env.pop("RUNTIME_DIRECTORY", None)
            proc = subprocess.Popen(
                [sys.executable, "-m", "ftsensord", "run", "--config", str(config)],
                env=env,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
            time.sleep(delay)
            proc.send_signal(signal.SIGTERM)
            code = proc.wait(timeout=30)
            run = folder / "ftsensord"
            out.append(
                {"delay_s": delay, "exit": code, "left": sorted(os.listdir(run)) if run.exists() else []}
            )
    return {"runs": out}


def first_status(runs: int) -> dict[str, Any]:
    """The first and second `status` (ms, handled and encoded) in ``runs`` fresh processes."""
    code = """
import json, sys, time
from pathlib import Path
from ftsensord.testing.harness import InProcess, packaged_config
from ftsensord.config.file import load_config
from ftsensord.sim.scene import default_scene
rig = InProcess(load_config(packaged_config(Path(sys.argv[1]) / "c.toml")), default_scene())
for _ in range(3):
    rig.daemon.cycle()
times = []
for _ in range(2):
    t0 = time.perf_counter()
    json.dumps(rig.daemon.control.handle(b'{"cmd": "status"}', [b"x"]), default=float)
    times.append((time.perf_counter() - t0) * 1e3)
    rig.daemon.cycle()  # a new cycle: the second is built anew, not cached
print(json.dumps(times))
"""
    out = []
    for _ in range(runs):
        with tempfile.TemporaryDirectory() as tmp:
            done = subprocess.run(
                [sys.executable, "-c", code, tmp], capture_output=True, text=True, check=True
            )
            out.append([round(t, 2) for t in json.loads(done.stdout)])
    return {"runs": runs, "first_second_ms": out}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "mode", choices=("descriptors", "unread", "stalled", "calibration", "early-stop", "first-status")
    )
    parser.add_argument("--connections", type=int, default=3000, help="descriptors: held on each socket")
    parser.add_argument(
        "--clients",
        type=int,
        default=127,
        help="unread: DEALER clients; stalled: SUBs (at most 127: the daemon keeps 128 "
        "connections a socket, and this script's control client or recorder takes one)",
    )
    parser.add_argument("--seconds", type=float, default=20.0, help="stalled: how long they stay")
    parser.add_argument("--requests", type=int, default=1000, help="unread: requests each")
    parser.add_argument(
        "--runs", type=int, default=20, help="calibration: loads timed; first-status: processes"
    )
    parser.add_argument("--delays", default="0.02,0.1,0.3,0.5,0.7,0.9", help="early-stop: s after the start")
    args = parser.parse_args()
    alone = {
        "calibration": lambda: calibration(args.runs),
        "first-status": lambda: first_status(args.runs),
        "early-stop": lambda: early_stop([float(d) for d in args.delays.split(",")]),
    }
    if args.mode in alone:
        print(json.dumps(alone[args.mode](), indent=1))
        return
    unit = UnitRestrictions.from_unit(UNIT)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        config = packaged_config(folder / "ftsensord.toml")
        memory = (
            MemoryGroup.make(unit.memory_max, f"ftsensord-hostile-{os.getpid()}") if unit.memory_max else None
        )
        try:
            proc, notify = sandboxed(config, folder, unit, memory)
            try:
                run = folder / "ftsensord"
                out = {
                    "descriptors": lambda: descriptors(run, proc, args.connections),
                    "unread": lambda: unread(run, proc, args.clients, args.requests),
                    "stalled": lambda: stalled(run, proc, args.clients, args.seconds),
                }[args.mode]()
                out["limit_nofile"] = unit.limit_nofile
                out["memory_max"] = unit.memory_max
                out["seccomp"] = bool(unit.filters)
            finally:
                try:
                    out_code = stop(proc, notify)
                finally:
                    if proc.poll() is None:  # stop timed out: the group cannot go while it lives
                        proc.kill()
                        proc.wait()
            out["exit_code"] = out_code
            # The cgroup's own count (page cache included, as the limit counts it), where enforced.
            peak = None if memory is None else memory.peak()
            out["memory_group"] = (
                None
                if memory is None
                else {
                    "v2": memory.v2,
                    "peak_mib": None if peak is None else round(peak / 2**20, 1),
                    "oom_kills": memory.oom_kills(),
                }
            )
        finally:
            if memory is not None:
                memory.remove()
        print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
