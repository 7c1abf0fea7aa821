"""The daemon's own CPU per cycle, beside a minimal numpy loop doing the same work, in one run.

The daemon (`ftsensord.service.daemon.Daemon`, the default configuration: 16 chips, two
sensors of 8, the tool tip, five publishes over ipc) cycles on `InstantBus`, a bus that
answers like 16 healthy chips at once, so what is counted is the daemon, not a bus. The
reference loop reads the same 16 chips from the same bus in one prebuilt ioctl, decodes the
block with one numpy pass (status bytes, words to tesla), computes K A (b - b0) for both
sensors and the tip, encodes the five frames and sends them: the least any implementation
must do. The two are measured in alternating rounds (``--rounds``) and the medians compared,
so a busy host slows both alike.

A slower CPU is not emulated: the process is pinned to one core (``--cpu``, so no
migration between cores), and the figures are also shown times ``--pi-factor`` (default 4),
a stated estimate of how much slower a Raspberry Pi 4 (Cortex-A72, 1.5 GHz) runs this kind
of CPython and numpy code than a current x86 core; it is an assumption, not a measurement:
run this script on the board for its own figures.

    python benchmarks/cycle_cpu.py                 # the docs' figures (about a minute)
    python benchmarks/cycle_cpu.py --quick --json  # CI: a few hundred cycles, one JSON object
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import platform
import statistics
import tempfile
import time
from typing import Any

import numpy as np
import zmq
from smbus2 import i2c_msg

from ftsensord.chip import mlx90393 as mlx
from ftsensord.model import se3
from ftsensord.service import wire
from ftsensord.service.config import Config, builtin_path, load_config
from ftsensord.service.daemon import Daemon
from ftsensord.sim import NoiseModel, default_scene

#: Readings a chip cycles through: at the default settings' noise (a third of the words'
#: 6 uT LSB) the same words come back often, never for as many cycles as the stuck test needs.
READINGS = 64


class InstantBus:
    """Answers like healthy chips at once: RM from `READINGS` precomputed readings a chip,
    in turn (the default scene's flux at rest with the emulated chip's noise, quantised as
    the chip does: healthy readings, so the redundancy check passes as it does on a sensor
    at rest and no chip looks stuck), RR from the configured registers, the real chip's
    status bytes otherwise."""

    def __init__(self, config: Config):
        settings = config.settings
        self.regs = settings.to_registers()
        scene = default_scene()  # the room and part the packaged calibrations were fitted on
        rng = np.random.default_rng(0)
        noise = NoiseModel()
        self.replies: dict[tuple[int, int], list[bytes]] = {}
        for a in config.addresses:
            truth_ut = scene.field_t(a, 0.0) * 1e6
            data = [b"".join(mlx.counts_to_raw(round((b + rng.normal(0.0, noise.sigma_ut(ax, settings.tconvm_us())))
                                                     / settings.sensitivity_ut(ax)), settings.raw_format(ax))
                             .to_bytes(2, "big") for b, ax in zip(truth_ut, "xyz"))
                    for _ in range(READINGS)]
            self.replies[(a, 7)] = [bytes([0x02]) + d for d in data]
            self.replies[(a, 9)] = [bytes([0x03]) + (46244).to_bytes(2, "big") + d for d in data]
        self.turn = dict.fromkeys(config.addresses, 0)

    def i2c_rdwr(self, *msgs: i2c_msg) -> None:
        # As cheap as Python allows (the first bytes only, no copies): the bus is not measured.
        write, address = None, 0
        for m in msgs:
            if m.flags & 1:
                reply = self._reply(address, write, m.len)
                ctypes.memmove(m.buf, reply, m.len)
            else:
                write, address = m, m.addr

    def _reply(self, address: int, write: Any, n: int) -> bytes:
        op = write.buf[0][0] & 0xF0
        if op == mlx.CMD_RM:
            k = self.turn[address] = (self.turn[address] + 1) % READINGS
            return self.replies[(address, n)][k]
        if op == mlx.CMD_RR:
            reg = write.buf[1][0] >> 2
            value = self.regs.get(reg, mlx.TREF_TYPICAL if reg == mlx.REG_TREF else 0)
            return b"\x00" + value.to_bytes(2, "big")
        # The real chip's D1:D0 in replies without data (docs/simulator.md).
        return {mlx.CMD_RT: b"\x05", mlx.CMD_SM: b"\x21", mlx.CMD_SB: b"\x81"}.get(op, b"\x01")

    def sleep(self, s: float) -> None:
        pass

    def monotonic(self) -> float:
        return time.monotonic()

    def close(self) -> None:
        pass


class Reference:
    """The minimal loop: one ioctl for every chip's RM, one numpy decode, K A, tip, five sends."""

    def __init__(self, config: Config, bus: InstantBus, publisher: zmq.Socket):
        self.bus, self.publisher = bus, publisher
        n, L = len(config.addresses), 7
        self.block = np.zeros((n, L), dtype=np.uint8)
        base = self.block.ctypes.data
        self.msgs = [m for i, a in enumerate(config.addresses) for m in (
            i2c_msg.write(a, bytes([mlx.CMD_RM | mlx.ZYXT_XYZ])),
            i2c_msg(addr=a, flags=1, len=L, buf=ctypes.cast(base + i * L, ctypes.POINTER(ctypes.c_char))))]
        fmt = config.settings.raw_format("x")
        self.zero = fmt.zero
        self.scale = np.array([config.settings.sensitivity_ut(a) * 1e-6 for a in "xyz"])
        self.models = [(s.name, s.calibration.model.KA, s.calibration.model.zero) for s in config.sensors]
        self.tip = [se3.wrench_transform(config.tool_poses[name]) for name, _, _ in self.models]
        self.seq = 0

    def cycle(self) -> None:
        self.bus.i2c_rdwr(*self.msgs)
        status = self.block[:, 0]
        if np.any(status & mlx.STATUS_ERROR):
            raise RuntimeError("a chip refused")  # never on the instant bus: only the check's cost
        words = (self.block[:, 1::2].astype(np.int32) << 8) | self.block[:, 2::2]
        flux = ((words - self.zero) * self.scale).reshape(len(self.models), -1)
        t_mono, t_wall = time.monotonic(), time.time()
        wrenches = [(b - zero) @ KA.T for (_, KA, zero), b in zip(self.models, flux)]
        tip = sum(X @ w for X, w in zip(self.tip, wrenches))
        frames = [wire.encode(f"wrench/{name}", wire.KIND_WRENCH, self.seq, t_mono, t_wall, 0, w)
                  for (name, _, _), w in zip(self.models, wrenches)]
        frames.append(wire.encode("wrench/tip", wire.KIND_WRENCH, self.seq, t_mono, t_wall, 0, tip))
        frames += [wire.encode(f"flux/{name}", wire.KIND_FLUX, self.seq, t_mono, t_wall, 0, b)
                   for (name, _, _), b in zip(self.models, flux)]
        for f in frames:
            self.publisher.send(f, zmq.NOBLOCK)
        self.seq += 1


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
    total = per_cycle_us(daemon.cycle, cycles)
    out = {k: v / cycles * 1e6 for k, v in spent.items()}
    out["rest"] = total - sum(out.values())
    return out


def measure(cycles: int, rounds: int, readback_every: int | None = None) -> dict[str, Any]:
    """Median CPU per cycle (us) of the daemon (linear, nonlinear) and the reference loop;
    ``readback_every`` (None: the configuration's, every cycle) for the daemons."""
    config = load_config(builtin_path("sim.toml"))
    ctx = zmq.Context()
    out: dict[str, list[float]] = {"linear": [], "nonlinear": [], "reference": []}
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
        reference = Reference(config, InstantBus(config), pub)
        for _ in range(50):
            reference.cycle()
        for _ in range(rounds):
            out["reference"].append(per_cycle_us(reference.cycle, cycles))
            out["linear"].append(per_cycle_us(daemons["linear"].cycle, cycles))
            out["nonlinear"].append(per_cycle_us(daemons["nonlinear"].cycle, max(1, cycles // 4)))
        for s in daemons["nonlinear"].sensors:
            estimate_us.append(s.status()["estimate_cpu_us"]["mean"])
        parts = breakdown(daemons["linear"], cycles)
        failing = sum(d.chips.failing for d in daemons.values())
        inconsistent = sum(s.check.inconsistent for d in daemons.values() for s in d.sensors)
        pub.close()
    ctx.term()
    med = {k: statistics.median(v) for k, v in out.items()}
    return {"cycles": cycles, "rounds": rounds, "samples": {k: v for k, v in out.items()},
            "reference_us": med["reference"], "daemon_linear_us": med["linear"],
            "daemon_nonlinear_us": med["nonlinear"], "ratio": med["linear"] / med["reference"],
            # Each round's ratio to the reference round just before it (the same moment of a busy
            # host's load), their median: beside the ratio of medians, a check on drifting load.
            "ratio_paired": statistics.median(d / r for d, r in zip(out["linear"], out["reference"])),
            "nonlinear_per_sensor_us": (med["nonlinear"] - med["linear"]) / len(config.sensors),
            "estimate_per_sensor_us": statistics.mean(estimate_us), "failing_chips": failing,
            "inconsistent_samples": inconsistent,
            "linear_breakdown_us": parts}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a few hundred cycles (CI): the structure, not figures")
    parser.add_argument("--cycles", type=int, default=1000, help="cycles a round (default 1000)")
    parser.add_argument("--rounds", type=int, default=7, help="alternating rounds (default 7)")
    parser.add_argument("--cpu", type=int, default=None, help="pin to this core (default: the last one)")
    parser.add_argument("--pi-factor", type=float, default=4.0,
                        help="stated slow-down of a Raspberry Pi 4 against this host (an estimate; default 4)")
    parser.add_argument("--readback-every", type=int, default=None,
                        help="the daemon's register read-back, cycles (default: the configuration's, 1; 0: none)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args()
    cycles, rounds = (100, 3) if args.quick else (args.cycles, args.rounds)
    cpu = args.cpu if args.cpu is not None else max(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {cpu})
    load = os.getloadavg()[0]
    r = measure(cycles, rounds, args.readback_every)
    r.update({"pinned_cpu": cpu, "load_1min": load, "pi_factor": args.pi_factor,
              "pi_estimate_linear_us": r["daemon_linear_us"] * args.pi_factor,
              "pi_estimate_nonlinear_per_sensor_us": r["nonlinear_per_sensor_us"] * args.pi_factor,
              "machine": f"{os.cpu_count()}-core {platform.machine()}, Python {platform.python_version()}",
              "quick": args.quick, "readback_every": args.readback_every})
    if args.json:
        print(json.dumps(r, indent=2))
        return 0
    print(f"{r['machine']}, pinned to core {cpu}, load {load:.2f}; {rounds} rounds of {cycles} cycles "
          f"(nonlinear: {max(1, cycles // 4)}), medians"
          + ("" if args.readback_every is None else f"; register read-back every {args.readback_every} cycles"))
    print(f"reference loop      {r['reference_us']:8.1f} us a cycle")
    print(f"daemon, linear      {r['daemon_linear_us']:8.1f} us a cycle  ({r['ratio']:.2f}x the reference; "
          f"target <= 5x; round by round {r['ratio_paired']:.2f}x)")
    parts = r["linear_breakdown_us"]
    print("  of which " + ", ".join(f"{k} {v:.0f} us" for k, v in parts.items()) + " (another run, wrapped)")
    print(f"daemon, nonlinear   {r['daemon_nonlinear_us']:8.1f} us a cycle  "
          f"({r['nonlinear_per_sensor_us']:.0f} us a sensor more than linear; the estimate alone "
          f"{r['estimate_per_sensor_us']:.0f} us; target <= 300)")
    print(f"x {args.pi_factor:g} (a stated estimate for a Pi 4, not measured): linear "
          f"{r['pi_estimate_linear_us']:.0f} us, nonlinear {r['pi_estimate_nonlinear_per_sensor_us']:.0f} us a sensor")
    if r["failing_chips"]:
        print(f"warning: {r['failing_chips']} chip(s) failing at the end: the figures include recovery")
    if r["inconsistent_samples"]:
        print(f"warning: {r['inconsistent_samples']} sample(s) flagged inconsistent: the figures include "
              "the redundancy check's search for the chip at fault")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
