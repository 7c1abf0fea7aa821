"""The daemon's own CPU per cycle, beside a minimal numpy loop doing the same work, in one run.

The daemon (`ftsensord.daemon.daemon.Daemon`, the default configuration: 16 chips, two
sensors of 8, the tool tip, five publishes over ipc) cycles on `InstantBus`, a stand-in
bus that answers like 16 healthy chips at once. The stand-in's own Python is not the
daemon's: its ioctls are recorded and replayed on it alone (`Recorded`), and that time,
printed on its own line, is taken out of the daemon's cycle. The reference loop has no bus
and nothing of ours inside (`Reference`): it decodes the 16 chips' replies (the stand-in's
bytes) in one numpy pass, computes K A (b - b0) for both sensors and the tip, encodes the
five frames with `struct` and sends them: the least any implementation must do once the
bytes are in. They are measured in alternating rounds (``--rounds``) and the medians
compared, so a busy host slows both alike.

A slower CPU is not emulated: the process is pinned to one core (``--cpu``, so no
migration between cores), and the figures are also shown times ``--pi-factor`` (default 4),
a stated estimate of how much slower a Raspberry Pi 4 (Cortex-A72, 1.5 GHz) runs this kind
of CPython and numpy code than a current x86 core; it is an assumption, not a measurement:
run this script on the board for its own figures.

    python -m benchmarks.performance.cycle_cpu                 # the docs' figures (about a minute)
    python -m benchmarks.performance.cycle_cpu --quick --json  # CI: a few hundred cycles, one JSON object
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import struct
import tempfile
import time
from typing import Any

import numpy as np
import zmq

from benchmarks.common import READINGS, InstantBus, machine, pin_to_core
from ftsensord.chip import mlx90393 as mlx
from ftsensord.config.file import Config, builtin_path, load_config
from ftsensord.daemon.daemon import Daemon
from ftsensord.model import se3

#: The wire's header as docs/reference/protocol.md gives it (magic, version, kind, flags, seq, t_mono,
#: t_wall, count, reserved, reserved), written out here so the reference uses nothing of ours.
REF_HEADER = struct.Struct("<HBBIQddHHI")


class Reference:
    """The minimal loop, with no bus and nothing of ours inside: the 16 chips' RM replies
    (the instant bus's, `READINGS` blocks of them, one taken in turn) decoded in one numpy
    pass (status check, words, tesla), K A (b - b0) per sensor, the tip, five frames
    encoded with `struct` and sent. What any implementation must do once the bytes are in."""

    def __init__(self, config: Config, bus: InstantBus, publisher: zmq.Socket):
        self.publisher = publisher
        n = len(config.addresses)
        replies = [bus.replies[(a, 7)] for a in config.addresses]
        self.blocks = [
            np.frombuffer(b"".join(r[k] for r in replies), dtype=np.uint8).reshape(n, 7)
            for k in range(READINGS)
        ]
        self.zero = np.int32(
            config.settings.raw_format("x").zero
        )  # a numpy int32: the words' difference is one
        self.scale = np.array([config.settings.sensitivity_ut(a) * 1e-6 for a in "xyz"])
        self.error_bit = mlx.STATUS_ERROR
        self.models = [(s.calibration.model.KA, s.calibration.model.zero) for s in config.sensors]
        self.tip = [se3.wrench_transform(config.tool_poses[s.name]) for s in config.sensors]
        self.topics = (
            [f"wrench/{s.name}\0".encode() for s in config.sensors]
            + [b"wrench/tip\0"]
            + [f"flux/{s.name}\0".encode() for s in config.sensors]
        )
        self.seq = self.turn = 0

    def cycle(self) -> None:
        block = self.blocks[self.turn]
        self.turn = (self.turn + 1) % READINGS
        if np.any(block[:, 0] & self.error_bit):
            raise RuntimeError("a chip refused")  # never with these replies: only the check's cost
        words = block[:, 1:].view(">u2")  # the big-endian words after the status byte
        flux = ((words - self.zero) * self.scale).reshape(len(self.models), -1)
        t_mono, t_wall = time.monotonic(), time.time()
        wrenches = [(b - zero) @ KA.T for (KA, zero), b in zip(self.models, flux)]
        values = [*wrenches, self.tip[0] @ wrenches[0] + self.tip[1] @ wrenches[1], *flux]
        seq, send, pack = self.seq, self.publisher.send, REF_HEADER.pack
        for topic, kind, v in zip(self.topics, (1, 1, 1, 2, 2), values):
            send(
                topic + pack(0x5446, 1, kind, 0, seq, t_mono, t_wall, len(v), 0, 0) + v.tobytes(), zmq.NOBLOCK
            )
        self.seq += 1


class Recorded:
    """The ioctls a daemon made over ``cycles`` cycles, replayed on its stand-in bus alone:
    the stand-in's own Python a cycle, measured apart from the daemon."""

    def __init__(self, daemon: Daemon, cycles: int):
        self.calls: list[tuple[Any, ...]] = []
        bus = daemon.bus
        inner = bus.i2c_rdwr
        bus.i2c_rdwr = lambda *msgs: (self.calls.append(msgs), inner(*msgs))[1]  # type: ignore[method-assign]
        for _ in range(cycles):
            daemon.cycle()
        del bus.i2c_rdwr  # the class's method again
        self.cycles = cycles
        self.bus = bus

    def replay(self) -> None:
        rdwr = self.bus.i2c_rdwr
        for msgs in self.calls:
            rdwr(*msgs)


def per_cycle_us(step: Any, cycles: int) -> float:
    t0 = time.process_time()
    for _ in range(cycles):
        step()
    return (time.process_time() - t0) / cycles * 1e6


def breakdown(daemon: Daemon, cycles: int) -> dict[str, float]:
    """Where a linear cycle's CPU goes (us a cycle): the reader (bus, decode, health,
    the register read-back), each sensor's flux and estimate, and the rest (tip, encode,
    send, bookkeeping); timed by wrapping those calls, so a little is the wrappers'."""
    spent = {"read": 0.0, "flux": 0.0, "estimate": 0.0}

    def timed(name: str, f: Any) -> Any:
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            t0 = time.process_time()
            try:
                return f(*args, **kwargs)
            finally:
                spent[name] += time.process_time() - t0

        return wrapper

    daemon.reader.read = timed("read", daemon.reader.read)  # type: ignore[method-assign]
    daemon.reader.upkeep = timed("read", daemon.reader.upkeep)  # type: ignore[method-assign]
    for p in daemon.sensors:
        p.flux = timed("flux", p.flux)  # type: ignore[method-assign]
        p.estimate = timed("estimate", p.estimate)  # type: ignore[method-assign]
        p.check.usual = timed("estimate", p.check.usual)  # type: ignore[method-assign]  # the usual sample's
    total = per_cycle_us(daemon.cycle, cycles)
    out = {k: v / cycles * 1e6 for k, v in spent.items()}
    out["rest"] = total - sum(out.values())
    return out


#: Cycles whose ioctls are recorded to time the stand-in bus alone: a multiple of the
#: temperature's 100 (`temperature_every`) and of the 16 chips' read-back turns' 16.
RECORDED_CYCLES = 400


def measure(cycles: int, rounds: int, readback_every: int | None = None) -> dict[str, Any]:
    """Median CPU per cycle (us) of the daemon (linear, nonlinear), of the stand-in bus's
    own Python inside the linear daemon's cycle, and of the reference loop;
    ``readback_every`` (None: the configuration's, every cycle) for the daemons."""
    config = load_config(builtin_path("sim.toml"))
    ctx = zmq.Context()
    out: dict[str, list[float]] = {"linear": [], "nonlinear": [], "reference": [], "bus": []}
    estimate_us: list[float] = []
    with tempfile.TemporaryDirectory() as tmp:
        pub = ctx.socket(zmq.PUB)
        pub.setsockopt(zmq.LINGER, 0)
        pub.bind(f"ipc://{tmp}/pub")
        daemons = {}
        for estimator in ("linear", "nonlinear"):
            cfg = load_config(builtin_path("sim.toml"))
            if readback_every is not None:
                cfg.readback_every = readback_every
            for s in cfg.sensors:
                s.estimator = estimator
            d = daemons[estimator] = Daemon(cfg, InstantBus(cfg), pub, None)
            d.start()
            for _ in range(50):  # warm: shapes learnt, plans built, the estimator's pose found
                d.cycle()
        recorded = Recorded(daemons["linear"], RECORDED_CYCLES)
        replays = max(1, cycles // RECORDED_CYCLES)
        reference = Reference(config, InstantBus(config), pub)
        for _ in range(50):
            reference.cycle()
        for _ in range(rounds):
            out["reference"].append(per_cycle_us(reference.cycle, cycles))
            out["linear"].append(per_cycle_us(daemons["linear"].cycle, cycles))
            out["bus"].append(per_cycle_us(recorded.replay, replays) / RECORDED_CYCLES)
            out["nonlinear"].append(per_cycle_us(daemons["nonlinear"].cycle, max(1, cycles // 4)))
        for s in daemons["nonlinear"].sensors:
            estimate_us.append(statistics.fmean(s.estimate_s) * 1e6)
        parts = breakdown(daemons["linear"], cycles)
        failing = sum(d.chips.failing for d in daemons.values())
        inconsistent = sum(s.check.inconsistent for d in daemons.values() for s in d.sensors)
        pub.close()
    ctx.term()
    med = {k: statistics.median(v) for k, v in out.items()}
    own = [d - b for d, b in zip(out["linear"], out["bus"])]
    return {
        "cycles": cycles,
        "rounds": rounds,
        "samples": {k: v for k, v in out.items()},
        "reference_us": med["reference"],
        "daemon_linear_us": med["linear"],
        "bus_us": med["bus"],
        "daemon_own_us": statistics.median(own),
        "daemon_nonlinear_us": med["nonlinear"],
        # The daemon's own work (its cycle less the stand-in bus's Python) against the
        # minimal loop, which has no bus: the figure the target is about.
        "ratio": statistics.median(own) / med["reference"],
        # Each round's ratio to the reference round just before it (the same moment of a busy
        # host's load), their median: beside the ratio of medians, a check on drifting load.
        "ratio_paired": statistics.median(o / r for o, r in zip(own, out["reference"])),
        "ratio_with_bus": med["linear"] / med["reference"],
        "nonlinear_per_sensor_us": (med["nonlinear"] - med["linear"]) / len(config.sensors),
        "estimate_per_sensor_us": statistics.mean(estimate_us),
        "failing_chips": failing,
        "inconsistent_samples": inconsistent,
        "linear_breakdown_us": parts,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--quick", action="store_true", help="a few hundred cycles (CI): the structure, not figures"
    )
    parser.add_argument("--cycles", type=int, default=1000, help="cycles a round (default 1000)")
    parser.add_argument("--rounds", type=int, default=7, help="alternating rounds (default 7)")
    parser.add_argument("--cpu", type=int, default=None, help="pin to this core (default: the last one)")
    parser.add_argument(
        "--pi-factor",
        type=float,
        default=5.5,
        help="stated slow-down of a Pi 4 against this host (default 5.5: docs/results/performance.md)",
    )
    parser.add_argument(
        "--readback-every",
        type=int,
        default=None,
        help="the daemon's register read-back, cycles (default: the configuration's, 1; 0: none)",
    )
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args()
    cycles, rounds = (100, 3) if args.quick else (args.cycles, args.rounds)
    cpu = pin_to_core(args.cpu)
    load = os.getloadavg()[0]
    r = measure(cycles, rounds, args.readback_every)
    r.update(
        {
            "pinned_cpu": cpu,
            "load_1min": load,
            "pi_factor": args.pi_factor,
            "pi_estimate_linear_us": r["daemon_own_us"] * args.pi_factor,
            "pi_estimate_nonlinear_per_sensor_us": r["nonlinear_per_sensor_us"] * args.pi_factor,
            "machine": machine(),
            "quick": args.quick,
            "readback_every": args.readback_every,
        }
    )
    if args.json:
        print(json.dumps(r, indent=2))
        return 0
    print(
        f"{r['machine']}, pinned to core {cpu}, load {load:.2f}; {rounds} rounds of {cycles} cycles "
        f"(nonlinear: {max(1, cycles // 4)}), medians"
        + ("" if args.readback_every is None else f"; register read-back every {args.readback_every} cycles")
    )
    print(f"reference loop      {r['reference_us']:8.1f} us a cycle  (no bus: decode, K A, tip, 5 sends)")
    print(
        f"stand-in bus        {r['bus_us']:8.1f} us a cycle  (InstantBus's own Python, its ioctls replayed)"
    )
    print(f"daemon, linear      {r['daemon_linear_us']:8.1f} us a cycle  (with the stand-in bus)")
    print(
        f"  less the bus      {r['daemon_own_us']:8.1f} us a cycle  ({r['ratio']:.2f}x the reference; "
        f"target <= 5x; round by round {r['ratio_paired']:.2f}x)"
    )
    parts = r["linear_breakdown_us"]
    print(
        "  of which "
        + ", ".join(f"{k} {v:.0f} us" for k, v in parts.items())
        + " (another run, wrapped; read with the stand-in bus)"
    )
    print(
        f"daemon, nonlinear   {r['daemon_nonlinear_us']:8.1f} us a cycle  "
        f"({r['nonlinear_per_sensor_us']:.0f} us a sensor more than linear; the estimate alone "
        f"{r['estimate_per_sensor_us']:.0f} us; at rest: a moving load is benchmarks/performance/nonlinear_cpu.py's)"
    )
    print(
        f"x {args.pi_factor:g} (a stated estimate for a Pi 4, not measured): linear "
        f"{r['pi_estimate_linear_us']:.0f} us, nonlinear {r['pi_estimate_nonlinear_per_sensor_us']:.0f} us a sensor"
    )
    if r["failing_chips"]:
        print(f"warning: {r['failing_chips']} chip(s) failing at the end: the figures include recovery")
    if r["inconsistent_samples"]:
        print(
            f"warning: {r['inconsistent_samples']} sample(s) flagged inconsistent: the figures include "
            "the redundancy check's search for the chip at fault"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
