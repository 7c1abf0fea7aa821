"""Which scheduler and register read-back hold a rate, and which levers move the bound.

The daemon chooses what a configuration leaves unnamed (`choose`): ``scheduler`` and
``readback_every``. The read-back (one chip's registers a cycle, docs/design/reliability.md)
is what catches a chip that reset or lost its settings, so it is kept while some
scheduler holds the rate with `TARGET_SPARE` of the period left; only when none does
is it given up, for the option with the most spare (a near tie keeps it). When nothing
holds, the error names every lever with the bound it would give (`levers`); where the
daemon runs anyway (a board measured slower than its file said), it runs the fastest
option (`fastest`). docs/design/performance.md, "The daemon's choice", has the figures.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from ftsensord.acquire.bound import SCHEDULERS, CycleBound, burst_readback_stays_fresh, cycle_bound
from ftsensord.chip import mlx90393 as mlx
from ftsensord.errors import ConfigError

#: docs/design/performance.md's target for the loop: 20 % of the period spare (the host's work
#: and the bus's jitter on a board fit in it).
TARGET_SPARE = 0.2
#: A burst chip read back restarts its burst (EX, RR, SB); where a cycle leaves it no time
#: for a new result, the read-back runs every this many cycles instead of every cycle.
SPARSE_READBACK_EVERY = 100
#: The MLX90393's fastest clock: fast mode (the datasheet has no fast-mode plus).
CHIP_MAX_CLOCK_HZ = 400e3
#: Options whose spares differ by less than 1 % of the period are a tie (the loop's own
#: jitter is larger: docs/design/performance.md), which the read-back wins.
TIE_SPARE = 0.01


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
        return cycle_bound(
            scheduler,
            self.n_chips,
            self.settings,
            self.clock_hz,
            self.ioctl_s,
            readback=readback,
            temperature=self.temperature,
            adapter=self.adapter,
        )


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
            self.readback_every, f"read-back every {self.readback_every} cycles"
        )
        return (
            f"{self.scheduler}, {readback}: bound {self.bound.rate_hz:.1f} Hz, "
            f"{self.spare(rate_hz):.0%} of the period spare at {rate_hz:g} Hz"
        )


def option(bus: Bus, scheduler: str, readback: bool, rate_hz: float) -> Option:
    """``scheduler`` with (or without) the read-back; a burst's every `SPARSE_READBACK_EVERY`
    cycles where one every cycle would leave the chip read back stale."""
    bound = bus.bound(scheduler, readback)
    every = int(readback)
    if (
        readback
        and scheduler == "burst"
        and not burst_readback_stays_fresh(bound, bus.settings, rate_hz, bus.temperature)
    ):
        every = SPARSE_READBACK_EVERY
    return Option(scheduler, every, bound)


def options(
    bus: Bus, rate_hz: float, scheduler: str | None = None, readback_every: int | None = None
) -> list[Option]:
    """The options a configuration leaves open: a named lever (not None) is kept as named."""
    if not rate_hz > 0:  # also NaN: a rate is a positive number of Hz
        raise ConfigError(f"rate: expected a positive number of Hz, got {rate_hz!r}")
    out = [
        option(bus, s, r, rate_hz)
        for s in (SCHEDULERS if scheduler is None else (scheduler,))
        for r in ((True, False) if readback_every is None else (readback_every > 0,))
    ]
    return out if readback_every is None else [Option(o.scheduler, readback_every, o.bound) for o in out]


def choose(
    bus: Bus, rate_hz: float, scheduler: str | None = None, readback_every: int | None = None
) -> Option:
    """The option that holds ``rate_hz`` among those the configuration leaves open (None:
    unnamed): with the read-back if one holds with `TARGET_SPARE`, else the most spare (a
    tie, `TIE_SPARE`, to the read-back). ConfigError, naming every lever, when none holds."""
    open_ = options(bus, rate_hz, scheduler, readback_every)
    holding = [
        o for o in open_ if o.spare(rate_hz) >= 0.0
    ]  # at the bound itself: the loop holds 0.955-1.000 of it (doctor)
    if not holding:
        raise ConfigError(
            f"{rate_hz:g} Hz cannot be met: {fastest(open_).bound.describe()}. "
            f"Levers: {levers(bus, rate_hz, scheduler, readback_every)}"
        )
    checked = [o for o in holding if o.readback_every and o.spare(rate_hz) >= TARGET_SPARE]
    if checked:
        return max(checked, key=lambda o: o.spare(rate_hz))
    most = max(o.spare(rate_hz) for o in holding)
    return max(
        (o for o in holding if o.spare(rate_hz) >= most - TIE_SPARE),
        key=lambda o: (o.readback_every > 0, o.spare(rate_hz)),
    )


def fastest(candidates: list[Option]) -> Option:
    """The option with the highest bound (where nothing holds and the loop runs anyway)."""
    return max(candidates, key=lambda o: o.bound.rate_hz)


def explain(
    bus: Bus, picked: Option, rate_hz: float, scheduler: str | None = None, readback_every: int | None = None
) -> str:
    """``picked`` described; with every lever when it leaves less than `TARGET_SPARE`
    (``scheduler``, ``readback_every``: what the configuration names, kept)."""
    spare = picked.spare(rate_hz)
    if spare >= TARGET_SPARE:
        return picked.describe(rate_hz)
    what = ("nothing holds the rate, the fastest runs: " if spare < 0 else "") + picked.describe(rate_hz)
    return (
        f"{what}, under the {TARGET_SPARE:.0%} target (the host's work may make cycles late). "
        f"Levers: {levers(bus, rate_hz, scheduler, readback_every, picked)}"
    )


def levers(
    bus: Bus,
    rate_hz: float,
    scheduler: str | None = None,
    readback_every: int | None = None,
    current: Option | None = None,
) -> str:
    """Every change that raises the bound above ``current``'s (None: the fastest option the
    configuration leaves open), each with the bound it gives (Hz, the read-back as now)."""
    current = current or fastest(options(bus, rate_hz, scheduler, readback_every))
    readback = current.readback_every > 0
    now = current.bound.rate_hz
    named = f"named {scheduler}; " if scheduler is not None else ""
    out = [
        f"the scheduler ({named}{'with' if readback else 'without'} the read-back: "
        + ", ".join(f"{s} {bus.bound(s, readback).rate_hz:.1f}" for s in SCHEDULERS)
        + " Hz)"
    ]
    if readback:
        out.append(
            "no register read-back, readback_every = 0 ("
            + ", ".join(f"{s} {bus.bound(s, False).rate_hz:.1f}" for s in SCHEDULERS)
            + " Hz)"
        )

    def better(what: str, changed: Bus) -> None:
        rate = changed.bound(current.scheduler, readback).rate_hz
        if rate > now:
            out.append(f"{what} ({current.scheduler} {rate:.1f} Hz)")

    if bus.temperature:
        better("no temperatures, temperature_every = 0", replace(bus, temperature=False))
    shorter = _shorter_conversion(bus.settings)
    if shorter is not None:
        better(
            f"a shorter conversion, OSR {shorter.osr} and DIG_FILT {shorter.dig_filt}",
            replace(bus, settings=shorter),
        )
    if bus.clock_hz < CHIP_MAX_CLOCK_HZ * 0.99:  # 1 %: a measured clock is never exact
        better(
            f"the bus clock at {CHIP_MAX_CLOCK_HZ / 1e3:.0f} kHz, now {bus.clock_hz / 1e3:.0f} kHz",
            replace(bus, clock_hz=CHIP_MAX_CLOCK_HZ),
        )
    # Rounded down: a rate the text names must hold.
    out.append(
        f"a lower rate (at most {_floor(now * (1 - TARGET_SPARE))} Hz for {TARGET_SPARE:.0%} spare, "
        f"{_floor(now)} Hz at the bound; now {rate_hz:g} Hz)"
    )
    return "; ".join(out)


def _floor(hz: float) -> str:
    return f"{int(hz * 10) / 10:g}"


def conversions(settings: mlx.Settings) -> list[mlx.Settings]:
    """Every permitted OSR and DIG_FILT with ``settings``' gain, HALLCONF and resolution."""
    out = []
    for osr in range(mlx.OSR.max + 1):
        for dig_filt in range(mlx.DIG_FILT.max + 1):
            candidate = replace(settings, osr=osr, dig_filt=dig_filt)
            try:
                candidate.validate()  # some pairs are forbidden at HALLCONF 0xC
            except ConfigError:
                continue
            out.append(candidate)
    return out


def _shorter_conversion(settings: mlx.Settings) -> mlx.Settings | None:
    """The permitted OSR and DIG_FILT whose conversion is the next shorter than today's
    (the least noise given up); None: already the shortest."""
    now = settings.tconvm_us()
    shorter = [c for c in conversions(settings) if c.tconvm_us() < now]
    return max(shorter, key=lambda c: c.tconvm_us()) if shorter else None
