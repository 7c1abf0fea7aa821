"""``ftsensord doctor``: bring a board up, and say what it can do.

`doctor` opens a bus (taking its lock: it refuses a bus a running daemon holds
unless forced), names the adapter and what it accepts in one ioctl, the
configured and the measured clock and the cost of one ioctl (`board`), finds
the chips (`scan`) and counts errors over a few hundred register reads each,
then per scheduler computes the bound for the chips found and runs a short
while at the fastest rate the bound allows, measuring the rate achieved. It
returns a plain dict (JSON as it is).

It disturbs the chips (EX, reconfiguration, modes): never on a bus a daemon
is using. On the simulated bus the run goes on the simulator's own clock
(virtual by default: instant and repeatable; ``real_time`` spends real time,
host CPU included).
"""

from __future__ import annotations

import math
from typing import Any

from ftsensord.acquire import choice
from ftsensord.acquire.board import know_board
from ftsensord.acquire.bound import SCHEDULERS, Shapes, cycle_bound
from ftsensord.acquire.bus import open_bus, parse_bus
from ftsensord.acquire.reader import Reader, probe_shapes
from ftsensord.acquire.scan import scan
from ftsensord.chip import mlx90393 as mlx
from ftsensord.chip.driver import MLX90393
from ftsensord.chip.i2c import Bus
from ftsensord.errors import ChipError, ConfigError

#: Register reads per chip to count errors over (CONF1..CONF3 in turn).
ERROR_READS = 300
#: Cycles of the short run per scheduler (after a few to settle).
RUN_CYCLES = 200
SETTLE_CYCLES = 5


class _TimedBus:
    """The bus as a short run's reader sees it, adding up the time spent inside transfers
    (wire and ioctl cost; on a busy host also the wait for a core) and inside the reader's
    waits (conversions); the rest of a cycle is the host's CPU between them."""

    def __init__(self, bus: Bus):
        self.bus, self.in_transfers, self.in_waits = bus, 0.0, 0.0

    def i2c_rdwr(self, *msgs: Any) -> None:
        t0 = self.bus.monotonic()
        try:
            self.bus.i2c_rdwr(*msgs)
        finally:
            self.in_transfers += self.bus.monotonic() - t0

    def sleep(self, seconds: float) -> None:
        t0 = self.bus.monotonic()
        self.bus.sleep(seconds)
        self.in_waits += self.bus.monotonic() - t0

    def monotonic(self) -> float:
        return self.bus.monotonic()

    def close(self) -> None:
        self.bus.close()


def _register_errors(bus: Bus, address: int, expected: dict[int, int], reads: int) -> dict[str, int]:
    """Read CONF1..CONF3 ``reads`` times in all; count what went wrong."""
    chip = MLX90393(bus, address, sleep=bus.sleep)
    regs = sorted(expected)
    counts = {"reads": reads, "no_answer": 0, "refused_or_bad_reply": 0, "wrong_value": 0}
    for k in range(reads):
        reg = regs[k % len(regs)]
        try:
            if chip.read_register(reg) != expected[reg]:
                counts["wrong_value"] += 1
        except ChipError as exc:
            counts["no_answer" if getattr(exc, "errno", None) is not None else "refused_or_bad_reply"] += 1
    return counts


def _short_run(
    bus: Bus,
    addresses: list[int],
    scheduler: str,
    settings: mlx.Settings,
    bus_hz: float,
    overhead_s: float,
    adapter: str | None,
    cycles: int,
) -> dict[str, Any]:
    """Run ``scheduler`` at its bound's rate for ``cycles``; the measured rate and errors."""
    probe = cycle_bound(scheduler, len(addresses), settings, bus_hz, overhead_s, adapter=adapter)
    run = choice.option(
        choice.Bus(len(addresses), settings, bus_hz, overhead_s, adapter, temperature=False),
        scheduler,
        True,
        probe.rate_hz,
    )  # the read-back's cadence as the daemon would run it
    bound, readback_every = run.bound, run.readback_every
    timed = _TimedBus(bus)
    chips = [MLX90393(timed, a, sleep=timed.sleep) for a in addresses]
    reader = Reader(timed, chips, scheduler, settings, bus_hz, overhead_s, readback_every=readback_every)
    failed = reader.start()
    period = bound.cycle_s
    errors = 0
    refused0 = getattr(bus, "refused", None)
    t_first = None
    idle = 0.0
    next_at = bus.monotonic()
    for k in range(SETTLE_CYCLES + cycles + 1):
        t_idle = bus.monotonic()
        bus.sleep(max(0.0, next_at - t_idle))
        if k == SETTLE_CYCLES:
            t_first = bus.monotonic()
            timed.in_transfers = timed.in_waits = 0.0
        elif k > SETTLE_CYCLES:
            idle += bus.monotonic() - t_idle
        if k == SETTLE_CYCLES + cycles:
            break
        next_at = max(next_at + period, bus.monotonic())  # late: start again from now, never catch up
        results = reader.read()
        reader.upkeep()
        if k >= SETTLE_CYCLES:
            errors += sum(not r.ok for r in results.values())
    assert t_first is not None
    elapsed = bus.monotonic() - t_first
    transfers, waits = timed.in_transfers, timed.in_waits
    reader.stop()
    out: dict[str, Any] = {
        "bound_hz": bound.rate_hz,
        "bound": bound.describe(),
        "ioctls_per_cycle": bound.ioctls,
        "measured_hz": cycles / elapsed if elapsed > 0 else math.inf,
        "cycles": cycles,
        "chip_errors": errors,
        "start_failures": {f"0x{a:02X}": str(e) for a, e in failed.items()},
        # Where a cycle's time went (us, mean): the bound counts transfers and waits only.
        "cycle_us": {
            "transfers": transfers / cycles * 1e6,
            "waits": waits / cycles * 1e6,
            "host": (elapsed - idle - transfers - waits) / cycles * 1e6,
            "idle": idle / cycles * 1e6,
            "bound": bound.cycle_s * 1e6,
        },
    }
    if refused0 is not None:  # the simulated bus counts what its adapter refused
        out["refused_ioctls"] = bus.refused - refused0  # type: ignore[attr-defined]
    return out


def doctor(
    spec: str,
    schedulers: tuple[str, ...] = SCHEDULERS,
    *,
    bus_hz: float = 400e3,
    force: bool = False,
    settings: mlx.Settings | None = None,
    error_reads: int = ERROR_READS,
    cycles: int = RUN_CYCLES,
    real_time: bool = False,
    rate_hz: float = 100.0,
) -> dict[str, Any]:
    """Everything `ftsensord doctor` reports, as a plain dict (see the module's doc).

    ``bus_hz`` is the clock ftsensord would be configured with (Hz); ``rate_hz`` the
    rate whose schedule the daemon would choose (`choice.choose`; temperatures read,
    as by default); ``force``
    goes on when another process holds the bus. Raises `BusBusyError` (held
    and not forced), `ConfigError` (a bad spec), ``OSError`` (no device).
    """
    settings = settings or mlx.Settings()
    options: dict[str, object] = {}
    if parse_bus(spec).kind == "sim":
        from ftsensord.sim import MonotonicClock, VirtualClock

        options = {"clock": MonotonicClock() if real_time else VirtualClock(), "bus_hz": bus_hz}
    bus = open_bus(spec, exclusive=True, force=force, **options)
    try:
        reports = scan(bus, settings)
        addresses = [r.address for r in reports]
        board = know_board(bus, addresses[0] if addresses else None, bus_hz)
        timing = board.timing
        clock_hz = timing.clock_hz or bus_hz
        ioctl_s = timing.ioctl_s if timing.ioctl_s is not None else 0.0
        shapes = (
            probe_shapes(bus, [MLX90393(bus, a, sleep=bus.sleep) for a in addresses]) if addresses else None
        )
        chips = []
        for r in reports:
            entry = r.as_dict()
            chip = MLX90393(bus, r.address, sleep=bus.sleep)
            try:
                expected = chip.read_configuration()
                entry["errors"] = _register_errors(bus, r.address, expected, error_reads)
            except ChipError as exc:
                entry["errors"] = {"reads": 0, "failed": str(exc)}
            chips.append(entry)
        runs = (
            {
                s: _short_run(bus, addresses, s, settings, clock_hz, ioctl_s, board.adapter, cycles)
                for s in schedulers
            }
            if addresses
            else {}
        )
        chosen = (
            _choice(
                choice.Bus(len(addresses), settings, clock_hz, ioctl_s, board.adapter, temperature=True),
                rate_hz,
            )
            if addresses
            else None
        )
    finally:
        bus.close()
    return {
        "bus": spec,
        "adapter": board.adapter,
        "driver": board.driver,
        "accepts": None
        if shapes is None
        else {
            "read_not_last": shapes.reads_inside,
            "several_addresses": shapes.many_addresses,
            "transfers": shapes.describe(),
        },
        "rules_counted": (shapes or Shapes.of(board.adapter)).describe(),
        "configured_clock_hz": board.configured_hz,
        "wanted_clock_hz": bus_hz,
        "clock_hz": clock_hz,
        "clock_measured": timing.clock_hz is not None,
        "ioctl_us": ioctl_s * 1e6,
        "warnings": board.warnings,
        "clock": "virtual" if options and not real_time else "real",
        "chips": chips,
        "schedulers": runs,
        "rate_hz": rate_hz,
        "choice": chosen,
    }


def _choice(bus: choice.Bus, rate_hz: float) -> dict[str, Any]:
    """What `ftsensord run` would choose at ``rate_hz`` with no scheduler or read-back named:
    ``scheduler``, ``readback_every``, ``bound_hz``, ``spare`` and ``text``; or ``error``."""
    try:
        picked = choice.choose(bus, rate_hz)
    except ConfigError as exc:
        return {"error": f"nothing holds: {exc}"}
    return {
        "scheduler": picked.scheduler,
        "readback_every": picked.readback_every,
        "bound_hz": picked.bound.rate_hz,
        "spare": picked.spare(rate_hz),
        "text": choice.explain(bus, picked, rate_hz),
    }


def format_doctor(report: dict[str, Any]) -> str:
    """The report as text for a person at a terminal."""
    lines = [
        f"bus {report['bus']}: adapter {report['adapter'] or 'unknown'} (driver {report['driver'] or '?'})"
    ]
    accepts = report["accepts"]
    lines.append(f"  one ioctl takes: {accepts['transfers'] if accepts else 'not probed (no chip answered)'}")
    measured = "measured" if report["clock_measured"] else "not measured, configured"
    configured = report["configured_clock_hz"]
    lines.append(
        f"  clock {report['clock_hz'] / 1e3:.1f} kHz ({measured}); kernel's "
        f"{'unknown' if configured is None else f'{configured / 1e3:.0f} kHz'}; "
        f"ioctl {report['ioctl_us']:.0f} us"
    )
    lines += [f"  WARNING: {w}" for w in report["warnings"]]
    for c in report["chips"]:
        errors = c["errors"]
        bad = sum(v for k, v in errors.items() if k not in ("reads", "failed") and isinstance(v, int))
        lines.append(
            f"  {c['address']} {c['part']}: B = {c['field_ut']} uT, T = {c['temperature_c']} degC, "
            f"{bad} errors in {errors.get('reads', 0)} register reads"
            + (f"; {c['error']}" if c["error"] else "")
        )
    if report["schedulers"]:
        lines.append("  each scheduler run at its bound, with the register read-back and no temperatures:")
    for name, run in report["schedulers"].items():
        t = run["cycle_us"]
        lines.append(
            f"  {name}: bound {run['bound_hz']:.1f} Hz, measured {run['measured_hz']:.1f} Hz at it "
            f"({run['cycles']} cycles, {run['chip_errors']} chip errors; a cycle: transfers "
            f"{t['transfers']:.0f} us, waits {t['waits']:.0f} us, host {t['host']:.0f} us, "
            f"bound {t['bound']:.0f} us)"
        )
    if report["choice"]:
        chosen = report["choice"]
        lines.append(
            f"  ftsensord run at {report['rate_hz']:g} Hz, no scheduler named (temperatures read): "
            f"{chosen.get('text') or chosen['error']}"
        )
    if not report["chips"]:
        lines.append("  no MLX90393 answered (0x0C-0x1B)")
    return "\n".join(lines)
