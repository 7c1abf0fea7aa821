"""Which scheduler and register read-back hold a rate, and which levers move the bound.

The daemon chooses what a configuration leaves unnamed (`choose`): ``scheduler`` and
``readback_every``. The read-back (one chip's registers a cycle, docs/reliability.md)
is what catches a chip that reset or lost its settings, so it is kept while some
scheduler holds the rate with `TARGET_SPARE` of the period left; only when none does
is it given up, for the option with the most spare. When nothing holds, the error
names every lever with the bound it would give (`levers`). docs/performance.md, "The
daemon's choice", has the figures.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from ..chip import mlx90393 as mlx
from ..errors import ConfigError
from .bound import SCHEDULERS, CycleBound, burst_readback_stays_fresh, cycle_bound

#: docs/performance.md's target for the loop: 20 % of the period spare (the host's work
#: and the bus's jitter on a board fit in it).
TARGET_SPARE = 0.2
#: A burst chip read back restarts its burst (EX, RR, SB); where a cycle leaves it no time
#: for a new result, the read-back runs every this many cycles instead of every cycle.
SPARSE_READBACK_EVERY = 100
#: The MLX90393's fastest clock: fast mode (the datasheet has no fast-mode plus).
CHIP_MAX_CLOCK_HZ = 400e3


@dataclass(frozen=True)
class Bus:
    """What a cycle's bound depends on besides the scheduler and read-back."""

    n_chips: int
    settings: mlx.Settings
    clock_hz: float  # the wire's clock (measured on a board, else configured), Hz
    ioctl_s: float  # one ioctl's fixed cost, s
    adapter: str | None  # `ADAPTER_RULES`' name; None: unknown, counted as the narrowest
    temperature: bool  # temperatures converted (temperature_every > 0)

    def bound(self, scheduler: str, readback: bool) -> CycleBound:
        return cycle_bound(scheduler, self.n_chips, self.settings, self.clock_hz, self.ioctl_s,
                           readback=readback, temperature=self.temperature, adapter=self.adapter)


@dataclass(frozen=True)
class Option:
    """A scheduler with a read-back cadence (0: none) and its bound."""

    scheduler: str
    readback_every: int
    bound: CycleBound

    def spare(self, rate_hz: float) -> float:
        """The part of the period (1 / ``rate_hz``) the bus leaves free."""
        return 1.0 - self.bound.cycle_s * rate_hz

    def describe(self, rate_hz: float) -> str:
        readback = {0: "no register read-back", 1: "read-back every cycle"}.get(
            self.readback_every, f"read-back every {self.readback_every} cycles")
        return (f"{self.scheduler}, {readback}: bound {self.bound.rate_hz:.1f} Hz, "
                f"{self.spare(rate_hz):.0%} of the period spare at {rate_hz:g} Hz")


def option(bus: Bus, scheduler: str, readback: bool, rate_hz: float) -> Option:
    """``scheduler`` with (or without) the read-back; a burst's every `SPARSE_READBACK_EVERY`
    cycles where one every cycle would leave the chip read back stale."""
    bound = bus.bound(scheduler, readback)
    every = int(readback)
    if readback and scheduler == "burst" and not burst_readback_stays_fresh(bound, bus.settings, rate_hz,
                                                                             bus.temperature):
        every = SPARSE_READBACK_EVERY
    return Option(scheduler, every, bound)


def choose(bus: Bus, rate_hz: float, scheduler: str | None = None, readback_every: int | None = None) -> Option:
    """The option that holds ``rate_hz`` among those the configuration leaves open (None:
    unnamed): with the read-back if one holds with `TARGET_SPARE`, else the most spare.
    A named lever is kept as named. ConfigError, naming every lever, when none holds."""
    schedulers = SCHEDULERS if scheduler is None else (scheduler,)
    readbacks = (True, False) if readback_every is None else (readback_every > 0,)
    options = [option(bus, s, r, rate_hz) for s in schedulers for r in readbacks]
    if readback_every is not None:
        options = [Option(o.scheduler, readback_every, o.bound) for o in options]
    holding = [o for o in options if o.spare(rate_hz) >= 0.0]  # at the bound itself: the loop holds 0.955-1.000 of it (doctor)
    if not holding:
        fastest = max(options, key=lambda o: o.bound.rate_hz)
        raise ConfigError(f"{rate_hz:g} Hz cannot be met on this bus: {fastest.bound.describe()}. "
                          f"Levers: {levers(bus, rate_hz)}")
    checked = [o for o in holding if o.readback_every and o.spare(rate_hz) >= TARGET_SPARE]
    return max(checked or holding, key=lambda o: o.spare(rate_hz))


def explain(bus: Bus, picked: Option, rate_hz: float) -> str:
    """``picked`` described; with every lever when it leaves less than `TARGET_SPARE`."""
    if picked.spare(rate_hz) >= TARGET_SPARE:
        return picked.describe(rate_hz)
    return (f"{picked.describe(rate_hz)}, under the {TARGET_SPARE:.0%} target (the host's work may make cycles "
            f"late). Levers: {levers(bus, rate_hz)}")


def levers(bus: Bus, rate_hz: float) -> str:
    """Every change that moves the bound, each with the best bound it gives (Hz)."""
    def best(b: Bus) -> str:  # the fastest scheduler's bound, with and without the read-back
        fastest = [max(b.bound(s, readback).rate_hz for s in SCHEDULERS) for readback in (True, False)]
        return f"{fastest[0]:.0f} Hz with the read-back, {fastest[1]:.0f} without"

    out = ["the scheduler (" + ", ".join(f"{s} {bus.bound(s, True).rate_hz:.0f}" for s in SCHEDULERS) + " Hz)",
           "no register read-back, readback_every = 0 (" +
           ", ".join(f"{s} {bus.bound(s, False).rate_hz:.0f}" for s in SCHEDULERS) + " Hz)"]
    if bus.temperature:
        out.append(f"no temperatures, temperature_every = 0 ({best(replace(bus, temperature=False))})")
    for name, key in (("OSR", "osr"), ("DIG_FILT", "dig_filt")):
        value = getattr(bus.settings, key)
        lower = replace(bus.settings, **{key: value - 1})
        try:
            lower.validate()  # 0 is the lowest, and some pairs are forbidden at HALLCONF 0xC
        except ConfigError:
            continue
        out.append(f"a shorter conversion, {name} {value - 1} ({best(replace(bus, settings=lower))})")
    if bus.clock_hz < CHIP_MAX_CLOCK_HZ * 0.99:  # 1 %: a measured clock is never exact
        out.append(f"the bus clock at {CHIP_MAX_CLOCK_HZ / 1e3:.0f} kHz, now {bus.clock_hz / 1e3:.0f} kHz "
                   f"({best(replace(bus, clock_hz=CHIP_MAX_CLOCK_HZ))})")
    top = max(bus.bound(s, False).rate_hz for s in SCHEDULERS)
    out.append(f"a lower rate (at most {top:.0f} Hz, now {rate_hz:g} Hz)")
    return "; ".join(out)
