"""Instructions a cycle or a sample, counted by valgrind's callgrind: exact and repeatable on
a shared host, where CPU time moves by 1.5x between runs minutes apart.

Each figure is the difference of two runs of the same process, one doing ``--short`` more
steps than the other after the same start and warm-up, divided by the extra steps: the
start (imports, building) cancels. What is counted (``what``):

- ``reference``: `cycle_cpu.Reference`'s cycle, the minimal loop with no bus;
- ``daemon``: the linear daemon's cycle on `cycle_cpu.InstantBus` (the default
  configuration; ``--readback-every`` as `cycle_cpu.py`'s);
- ``bus``: the stand-in bus's own Python inside that cycle (`cycle_cpu.Recorded`'s replay);
  the daemon's own work is ``daemon`` less ``bus``;
- ``nonlinear``: `nonlinear_cpu.py`'s moving readings (1.3 Hz, 40 % of range), one
  sensor's estimate each.

    python -m benchmarks.performance.instructions                  # all four, about 4 minutes
    python -m benchmarks.performance.instructions daemon bus --readback-every 0
    python -m benchmarks.performance.instructions daemon --skip check   # less the redundancy check: its cost

``--skip`` replaces one part of the daemon's cycle with nothing (``check``: the redundancy
check, every chip kept; ``judge``: the chips' health; ``count``: their counters;
``publish``: the five sends), so the difference from the full cycle is that part's cost.
The wrenches are then not checked: a figure of where the instructions go, not a daemon.

Needs valgrind on PATH. Python's hash seed and OpenBLAS's threads are fixed, so two runs
give the same counts to 0.1 %.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile

from benchmarks.common import ROOT

WARM = 60  # steps before counting: plans built, shapes learnt, the estimator's pose found
STEPS = {"reference": 400, "daemon": 400, "bus": 1600, "nonlinear": 200}


def _skip(daemon: object, parts: list[str]) -> None:
    """Each of ``parts`` of ``daemon``'s cycle replaced by nothing (`--skip`)."""
    for part in parts:
        if part == "check":
            for p in daemon.sensors:  # type: ignore[attr-defined]  # the separate way, unchecked
                p.check.usual = lambda pipeline, flux, usable: None
                p.check.chips = lambda pipeline, flux, usable: (usable, 0)
        elif part == "judge":  # the clean cycle's (`judge_words`) and any other's (`judge_all`)
            daemon.reader.care.judge_words = lambda *args: {}  # type: ignore[attr-defined]
            daemon.reader.care.judge_all = lambda *args: None  # type: ignore[attr-defined]
        elif part == "count":
            daemon.chips.count_all = lambda *args: None  # type: ignore[attr-defined]
        elif part == "publish":
            daemon._publish = lambda *args: None  # type: ignore[attr-defined]


def _child(what: str, steps: int, readback_every: int | None, skip: list[str]) -> None:
    """The process callgrind counts: ``WARM`` steps, then ``steps`` more."""
    import zmq

    from benchmarks.common import InstantBus
    from benchmarks.performance import cycle_cpu, nonlinear_cpu
    from ftsensord.config.file import builtin_path, load_config
    from ftsensord.daemon.daemon import Daemon

    config = load_config(builtin_path("sim.toml"))
    if what == "nonlinear":
        nl = config.sensors[0].calibration.nonlinear
        assert nl is not None  # the packaged calibrations have one
        flux, _ = nonlinear_cpu.readings(0.4, 1.3, 6)  # 462 readings: the longer run's 60 + 400
        if len(flux) < WARM + steps:
            raise SystemExit(f"{len(flux)} moving readings, {WARM + steps} needed: raise the periods")
        estimator = nl.estimator()
        for b in flux[: WARM + steps]:
            estimator.estimate(b)
        return
    if readback_every is not None:
        config.readback_every = readback_every
    with tempfile.TemporaryDirectory() as tmp:
        ctx = zmq.Context()
        pub = ctx.socket(zmq.PUB)
        pub.setsockopt(zmq.LINGER, 0)
        pub.bind(f"ipc://{tmp}/pub")
        if what == "reference":
            step = cycle_cpu.Reference(config, InstantBus(config), pub).cycle
        else:
            daemon = Daemon(config, InstantBus(config), pub, None)
            daemon.start()
            _skip(daemon, skip)
            step = daemon.cycle
            if what == "bus":  # the bus's Python alone: one replay is RECORDED_CYCLES cycles
                step = cycle_cpu.Recorded(daemon, cycle_cpu.RECORDED_CYCLES).replay
                steps //= cycle_cpu.RECORDED_CYCLES
        for _ in range(WARM if what != "bus" else 1):
            step()
        for _ in range(steps):
            step()
        pub.close()
        ctx.term()


SKIPPABLE = ("check", "judge", "count", "publish")


def count(what: str, steps: int, readback_every: int | None, skip: list[str]) -> int:
    """Instructions callgrind counts for one child process."""
    env = dict(
        os.environ,
        PYTHONHASHSEED="0",
        OPENBLAS_NUM_THREADS="1",
        PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
    )
    with tempfile.TemporaryDirectory() as tmp:
        args = [
            "valgrind",
            "--tool=callgrind",
            f"--callgrind-out-file={tmp}/out",
            sys.executable,
            "-m",
            "benchmarks.performance.instructions",
            "--child",
            what,
            str(steps),
        ] + ([] if readback_every is None else ["--readback-every", str(readback_every)])
        args += [a for part in skip for a in ("--skip", part)]
        done = subprocess.run(args, env=env, capture_output=True, text=True, check=True)
    found = re.search(r"Collected : (\d+)", done.stderr)
    if found is None:
        raise SystemExit(f"callgrind printed no count:\n{done.stderr[-2000:]}")
    return int(found.group(1))


def per_step(what: str, readback_every: int | None, skip: list[str]) -> float:
    extra = STEPS[what]
    return (count(what, 2 * extra, readback_every, skip) - count(what, extra, readback_every, skip)) / extra


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("what", nargs="*", help=f"what to count: {', '.join(STEPS)} (default all)")
    parser.add_argument(
        "--readback-every", type=int, default=None, help="the daemons' (default: the configuration's)"
    )
    parser.add_argument(
        "--skip",
        action="append",
        default=[],
        choices=SKIPPABLE,
        help="a part of the daemon's cycle to leave out (repeatable): its cost is the difference",
    )
    parser.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        _child(args.child[0], int(args.child[1]), args.readback_every, args.skip)
        return 0
    if set(args.what) - set(STEPS):
        parser.error(
            f"what to count: {', '.join(STEPS)}, not {', '.join(sorted(set(args.what) - set(STEPS)))}"
        )
    if shutil.which("valgrind") is None:
        raise SystemExit("valgrind is not on PATH (apt install valgrind)")
    got = {
        w: per_step(w, args.readback_every, args.skip if w == "daemon" else []) for w in args.what or STEPS
    }
    for w, n in got.items():
        print(f"{w:10s} {n:12,.0f} instructions a {'sample' if w == 'nonlinear' else 'cycle'}")
    if {"reference", "daemon", "bus"} <= got.keys():
        own = got["daemon"] - got["bus"]
        print(f"daemon's own {own:,.0f}: {own / got['reference']:.2f}x the reference")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
