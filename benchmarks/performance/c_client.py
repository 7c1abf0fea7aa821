"""What one "take the newest sample" call of clients/c/ftsensord.h costs a haptic loop.

Starts `ftsensord run` (the packaged simulated-bus configuration, 100 Hz), builds
benchmarks/performance/c_client.c against the header (libzmq found as clients/c/build.py says), runs
it for --ticks ticks of a 1 kHz loop on wrench/sensor1 over ipc, and reports the call's
duration per tick (p50, p99, max; all ticks, and the ticks that got a new sample, which
decode and copy it), the two clock reads' own cost, and the age of each new sample when
the loop first saw it. Run:

    python -m benchmarks.performance.c_client --ticks 10000     # the docs' figures (docs/guide/clients.md)
"""

from __future__ import annotations

import argparse
import os
import platform
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import load_c_build
from ftsensord.client import ControlClient


def percentiles(x: np.ndarray) -> str:
    return f"{np.percentile(x, 50):.2f} / {np.percentile(x, 99):.2f} / {x.max():.2f}"


def bench(ticks: int, topic: str) -> dict:
    build = load_c_build()
    libzmq = build.find_libzmq()
    with tempfile.TemporaryDirectory() as tmp:
        tmp_path = Path(tmp)
        program = tmp_path / "c_client"
        build.build([Path(__file__).with_suffix(".c")], program, "c", libzmq)
        env = {**os.environ, "XDG_RUNTIME_DIR": tmp}
        env.pop("RUNTIME_DIRECTORY", None)
        daemon = subprocess.Popen(
            [sys.executable, "-m", "ftsensord", "run"],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        try:
            folder = tmp_path / "ftsensord"
            control = ControlClient(f"ipc://{folder / 'control'}", timeout_s=5)
            for _ in range(100):
                if (folder / "control").exists():
                    break
                time.sleep(0.1)
            rate = control.status()["rate_hz"]
            out = subprocess.run(
                [str(program), f"ipc://{folder / 'wrench'}", topic, str(ticks)],
                capture_output=True,
                text=True,
                timeout=ticks / 1000 + 60,
                check=True,
            )
        finally:
            daemon.send_signal(signal.SIGTERM)
            daemon.wait(timeout=10)
    lines = out.stdout.splitlines()
    rows = np.array([[float(v) for v in line.split()] for line in lines if not line.startswith("timer_ns")])
    timer = np.array([float(line.split()[1]) for line in lines if line.startswith("timer_ns")]) / 1e3
    call_us, fresh, age_ms = rows[:, 0] / 1e3, rows[:, 1] > 0, rows[:, 2] / 1e6
    return {
        "ticks": len(rows),
        "fresh": int(fresh.sum()),
        "rate_hz": rate,
        "libzmq": libzmq.origin,
        "all": percentiles(call_us),
        "new": percentiles(call_us[fresh]),
        "same": percentiles(call_us[~fresh]),
        "timer": percentiles(timer),
        "age": percentiles(age_ms[fresh]),
        "client": out.stderr.strip(),
        "cpu": platform.processor() or platform.machine(),
        "cores": os.cpu_count(),
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--ticks", type=int, default=10000, help="ticks of the 1 kHz loop (default 10000)")
    parser.add_argument("--topic", default="wrench/sensor1")
    args = parser.parse_args()
    r = bench(args.ticks, args.topic)
    print(
        f"`python -m benchmarks.performance.c_client --ticks {args.ticks}`: {r['ticks']} ticks at 1 kHz, "
        f"{r['fresh']} new samples of {args.topic} from the daemon at {r['rate_hz']:g} Hz on the simulated bus, "
        f"{r['libzmq']}, {r['cores']} cores ({r['cpu']}); client: {r['client']}"
    )
    print()
    print("| per tick | p50 / p99 / max |")
    print("|---|---|")
    print(f"| `fts_latest`, every tick (us) | {r['all']} |")
    print(f"| `fts_latest`, ticks with a new sample: read, decode, copy (us) | {r['new']} |")
    print(f"| `fts_latest`, ticks without one (us) | {r['same']} |")
    print(f"| two `clock_gettime` calls alone, included above (us) | {r['timer']} |")
    print(f"| a new sample's age when the loop first got it (ms) | {r['age']} |")


if __name__ == "__main__":
    main()
