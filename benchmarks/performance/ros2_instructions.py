"""Instructions the in-loop ROS 2 output adds to the daemon's cycle, counted by callgrind
(benchmarks/performance/instructions.py's method: two runs of one process, one doing ``STEPS`` more
cycles after the same start and warm-up; the difference over the extra cycles).

The daemon is instructions.py's (the packaged configuration on `cycle_cpu.InstantBus`), its
``outputs`` as ``[ros2] output = "in-loop"`` sets them (`ftsensord.ros2.inloop.InLoop`):

- ``none``: no output (the daemon's own cycle);
- ``unread``: the output, no DDS reader (nothing written; the readers asked, the inputs polled);
- ``read``: a reliable DDS reader of ``wrench/sensor1`` in another process (not counted):
  one write a cycle, as in benchmarks/performance/ros2_latency.py;
- ``diagnostics``: as ``read``, each ``/diagnostics`` begun as soon as the last is written
  (the statuses made in one cycle, their bytes in the next few, `inloop.DIAGNOSTICS_A_CYCLE`
  statuses a cycle, the write with the last): the difference from ``read`` times the cycles
  one takes is one second's diagnostics, a hundredth of it a cycle's share at 100 Hz;
- ``diag-status``: as ``read``, the statuses made every other cycle, never encoded: twice
  the difference from ``read`` is the cycle that makes them; the rest of one diagnostics
  is the cycles that encode and write it.

Wall-clock timers (the readers asked five times a second, the diagnostics once) are held off
in the counted cycles: under valgrind a cycle lasts 50 times longer. Counted per thread
(``--separate-threads``): the loop's thread, and every thread of the process (DDS's own:
receive, timed events, delivery).

    python -m benchmarks.performance.ros2_instructions [none unread read diag-status diagnostics]
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.common import ROOT

WARM = 60  # as instructions.py: plans built, shapes learnt, the estimator's pose found
STEPS = 400
MATCH_S = 30.0  # discovery under valgrind: seconds, not milliseconds
VARIANTS = ("none", "unread", "read", "diag-status", "diagnostics")


def _child(what: str, steps: int) -> None:
    import zmq

    from benchmarks.performance import cycle_cpu
    from ftsensord.config.file import builtin_path, load_config
    from ftsensord.config.ros2conf import Ros2Config
    from ftsensord.daemon.daemon import Daemon

    config = load_config(builtin_path("sim.toml"))
    with tempfile.TemporaryDirectory() as tmp:
        ctx = zmq.Context()
        pub = ctx.socket(zmq.PUB)
        pub.setsockopt(zmq.LINGER, 0)
        pub.bind(f"ipc://{tmp}/pub")
        daemon = Daemon(config, cycle_cpu.InstantBus(config), pub, None)
        daemon.start()
        out = None
        if what != "none":
            from ftsensord.ros2.inloop import InLoop

            out = InLoop(daemon, Ros2Config("bench", int(os.environ["BENCH_DOMAIN"]), "in-loop"))
            daemon.outputs.append(out)
        for _ in range(WARM):
            daemon.cycle()
        if what in ("read", "diag-status", "diagnostics"):
            end = time.monotonic() + MATCH_S
            while not out.read and time.monotonic() < end:  # type: ignore[union-attr]
                out.find_readers()  # type: ignore[union-attr]
                # no cycles while discovery runs: as many as it took would be in one run's
                # count and not the other's (it takes seconds or tens of them, with the load)
                time.sleep(0.05)
            if not out.read:  # type: ignore[union-attr]
                raise SystemExit("the DDS reader was not matched")
        if out is not None:
            out.ask = float("inf")
            out.due = float("inf")
        begun = 0
        for i in range(steps):
            if what == "diagnostics" and out.pending is None:  # type: ignore[union-attr]
                out.due, begun = 0.0, begun + 1  # type: ignore[union-attr]
            elif what == "diag-status":  # made in the even cycles, dropped before the odd ones
                out.pending, out.due = None, 0.0 if i % 2 == 0 else float("inf")  # type: ignore[union-attr]
            daemon.cycle()
        pub.close()
        ctx.term()
        print(begun)  # diagnostics begun in the counted cycles


def count(what: str, steps: int, env: dict[str, str]) -> tuple[int, int, int]:
    """(the loop thread's, every thread's) instructions in one child process, and the
    diagnostics it began."""
    with tempfile.TemporaryDirectory() as tmp:
        args = [
            "valgrind",
            "--tool=callgrind",
            "--separate-threads=yes",
            f"--callgrind-out-file={tmp}/out",
            sys.executable,
            "-m",
            "benchmarks.performance.ros2_instructions",
            "--child",
            what,
            str(steps),
        ]
        begun = int(
            subprocess.run(args, env=env, capture_output=True, text=True, check=True).stdout.split()[-1]
        )
        totals = {}
        for f in Path(tmp).glob("out*"):
            found = re.search(r"^(?:totals|summary): (\d+)", f.read_text(errors="replace"), re.M)
            if found:
                totals[f.name] = int(found.group(1))
    if not totals:
        raise SystemExit("callgrind wrote no counts")
    main = totals.get("out-01", max(totals.values()))  # thread 1: the main thread, the loop's
    return main, sum(totals.values()), begun


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("what", nargs="*", help=f"what to count: {', '.join(VARIANTS)} (default all)")
    parser.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        _child(args.child[0], int(args.child[1]))
        return 0
    from benchmarks.performance.ros2_latency import DOMAIN, URI, dds_listen

    env = dict(
        os.environ,
        PYTHONHASHSEED="0",
        OPENBLAS_NUM_THREADS="1",
        CYCLONEDDS_URI=URI,
        BENCH_DOMAIN=str(DOMAIN),
        PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
    )
    os.environ["CYCLONEDDS_URI"] = URI
    got, cycles_a_diagnostics = {}, 0.0
    for what in args.what or VARIANTS:
        reader = None
        if what in (
            "read",
            "diag-status",
            "diagnostics",
        ):  # read throughout both runs; its receipts are not used
            reader = mp.Process(
                target=dds_listen,
                args=("rt/bench/wrench/sensor1", True, time.time() + 3600, mp.Queue()),
                daemon=True,
            )
            reader.start()
        try:
            (m1, a1, b1), (m2, a2, b2) = count(what, STEPS, env), count(what, 2 * STEPS, env)
        finally:
            if reader is not None:
                reader.kill()
                reader.join()
        got[what] = ((m2 - m1) / STEPS, (a2 - a1) / STEPS)
        if what == "diagnostics":
            cycles_a_diagnostics = STEPS / (b2 - b1)
        print(
            f"{what:12s} loop thread {got[what][0]:12,.0f}, all threads {got[what][1]:12,.0f} instructions a cycle",
            flush=True,
        )
    if "none" in got:
        for what, (m, a) in got.items():
            print(
                f"{what:12s} added: loop thread {m - got['none'][0]:+10,.0f}, all threads {a - got['none'][1]:+10,.0f}"
            )
    if {"read", "diagnostics"} <= got.keys():
        once = cycles_a_diagnostics * (got["diagnostics"][0] - got["read"][0])
        print(
            f"one /diagnostics (health, statuses, bytes, write; {cycles_a_diagnostics:g} cycles): {once:,.0f} "
            f"in the loop thread; {once / 100:,.0f} a cycle at 100 Hz"
        )
        if "diag-status" in got:
            built = 2 * (got["diag-status"][0] - got["read"][0])
            print(
                f"  the cycle making the statuses: {built:+,.0f}; the {cycles_a_diagnostics - 1:g} encoding and "
                f"writing them: {once - built:+,.0f}, {(once - built) / (cycles_a_diagnostics - 1):+,.0f} each"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
