"""`ftsensord record` stopped by each signal: received samples lost. Figures in docs/results/reliability.md.

    python -m benchmarks.robustness.record_signals --runs 2 --seconds 3

Starts `ftsensord run` (the default configuration: simulated bus, default scene) in
a private runtime folder and a Python `Subscriber` that receives every stream in
parallel (the reference). Per format (CSV, NPZ: wrench/sensor1; MCAP: wrench/sensor1,
wrench/tip and flux/sensor1) and per stop (SIGINT, SIGTERM, SIGHUP, SIGKILL) it runs
`ftsensord record` for --seconds, stops it, reads the file back (after a kill, as the
documented loaders read what is left: the NPZ sidecar, the CSV without a torn row,
the MCAP's complete chunks) and counts:

- samples in the file, and sequence numbers the reference received between the
  file's first and last that the file lacks (a hole: a received sample lost);
- lost at the end: samples the reference received with ``t_mono`` before the stop
  that come after the file's last one, and how long before the stop the newest
  of them was published (after a kill, what waited for its flush).
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from ftsensord.client import Subscriber
from ftsensord.recording import load_rows, read_mcap
from ftsensord.testing.harness import packaged_config, start_daemon, stop

SIGNALS = [signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGKILL]
FORMATS = {
    "csv": ["wrench/sensor1"],
    "npz": ["wrench/sensor1"],
    "mcap": ["wrench/sensor1", "wrench/tip", "flux/sensor1"],
}


def file_seqs(path: Path, streams: list[str]) -> dict[str, list[int]]:
    if path.suffix == ".csv":
        lines = path.read_text().splitlines(keepends=True)
        if lines and not lines[-1].endswith("\n"):
            lines.pop()
        return {streams[0]: [int(x.split(",")[0]) for x in lines[1:]]}
    if path.suffix == ".npz":
        part = Path(f"{path}.part")
        if not part.exists():
            return {streams[0]: np.load(path)["seq"].tolist()}
        # Empty: killed before the first sample arrived.
        return {streams[0]: load_rows(part)["seq"].tolist() if part.stat().st_size else []}
    out: dict[str, list[int]] = {s: [] for s in streams}
    for topic, msg, _ in read_mcap(path):
        if topic.endswith("/status"):
            out[topic[1 : -len("/status")]].append(msg.seq)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=2, help="runs per format and signal")
    ap.add_argument("--seconds", type=float, default=3.0, help="recording time before the signal")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="ftsensord-bench-"))
    env = {**os.environ, "XDG_RUNTIME_DIR": str(tmp)}
    env.pop("RUNTIME_DIRECTORY", None)
    daemon, notify = start_daemon(packaged_config(tmp / "ftsensord.toml"), tmp)
    pub = f"ipc://{tmp / 'ftsensord' / 'wrench'}"
    seen: dict[str, dict[int, float]] = {s: {} for s in FORMATS["mcap"]}
    done = threading.Event()

    def reference() -> None:
        with Subscriber(pub, FORMATS["mcap"]) as sub:
            while not done.is_set():
                s = sub.receive(timeout_s=0.1)
                if s is not None:
                    seen[s.topic][s.seq] = s.t_mono

    thread = threading.Thread(target=reference, daemon=True)
    thread.start()
    try:
        deadline = time.monotonic() + 30
        while not all(seen.values()):
            assert time.monotonic() < deadline, "the daemon published nothing in 30 s"
            time.sleep(0.1)
        rows = []
        for fmt, streams in FORMATS.items():
            for sig in SIGNALS:
                totals = {"samples": 0, "holes": 0, "end": 0, "end_s": 0.0}
                for run in range(args.runs):
                    path = tmp / f"{fmt}-{sig.name}-{run}.{fmt}"
                    t_start = time.monotonic()
                    proc = subprocess.Popen(
                        [sys.executable, "-m", "ftsensord", "record", *streams, str(path), "--endpoint", pub],
                        env=env,
                        stdout=subprocess.DEVNULL,
                        stderr=subprocess.DEVNULL,
                    )
                    time.sleep(args.seconds)
                    t_stop = time.monotonic()
                    proc.send_signal(sig)
                    proc.wait(timeout=30)
                    time.sleep(0.3)
                    for stream, seqs in file_seqs(path, streams).items():
                        ref = seen[stream]
                        totals["samples"] += len(seqs)
                        if not seqs:  # nothing on disk: every sample published while it ran is lost
                            totals["end"] += sum(1 for t in ref.values() if t_start <= t <= t_stop)
                            continue
                        totals["holes"] += sum(1 for q in ref if seqs[0] <= q <= seqs[-1]) - len(set(seqs))
                        after = [q for q, t in ref.items() if q > seqs[-1] and t <= t_stop]
                        totals["end"] += len(after)
                        if after:
                            totals["end_s"] = max(totals["end_s"], t_stop - min(ref[q] for q in after))
                rows.append((fmt, sig.name, totals))
    finally:
        done.set()
        thread.join(timeout=5)
        stop(daemon, notify)
    print(
        f"| format | stop | samples in the files ({args.runs} runs x {args.seconds:g} s) | received, lost "
        "(holes) | lost at the end | oldest lost at the end, ms before the stop |"
    )
    print("|---|---|---|---|---|---|")
    for fmt, sig, t in rows:
        print(f"| {fmt} | {sig} | {t['samples']} | {t['holes']} | {t['end']} | {t['end_s'] * 1e3:.1f} |")


if __name__ == "__main__":
    main()
