"""How fast each scheduler can read every chip: the computed cycle bound.

`cycle_bound` computes the fastest cycle each can achieve from the chip
settings, the bus clock and what the adapter accepts in one ioctl (`Shapes`:
the ioctls a cycle really takes, each with its fixed cost; docs/design/performance.md
has the figures), so the daemon can refuse a rate it cannot meet.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ftsensord.chip import mlx90393 as mlx
from ftsensord.chip.i2c import ADAPTER_RULES, BITS_PER_BYTE, I2C_RDWR_MAX_MSGS
from ftsensord.errors import ConfigError

SCHEDULERS = ("naive", "overlapped", "burst")
#: The chip's oscillator runs within +-20 % of nominal: wait for the slowest.
OSC_MARGIN = mlx.OSCILLATOR_SLOWEST
#: The chip read back in an overlapped cycle has its RM timed to reach it as its conversion
#: ends; this much later keeps round-off (~1e-18 s) from putting it a hair early on a chip
#: at the slow end of the oscillator's spread, and is under half a bit at 400 kHz.
READY_GUARD_S = 1e-6
#: Chips per transfer: two messages each, at most 42 messages an ioctl.
CHIPS_PER_TRANSFER = I2C_RDWR_MAX_MSGS // 2


@dataclass(frozen=True)
class Shapes:
    """What the reader puts in one ioctl, from what the adapter accepts.

    ``reads_inside``: a read may be followed by more messages; ``many_addresses``:
    one ioctl may reach several chips. Both (permissive): up to 21 chips' (write,
    read) pairs an ioctl. Otherwise one chip's (write, read) an ioctl: i2c-bcm2835
    takes a read only last (it would take writes to many chips then one read, but
    every command's status is read, so each chip's SM has its read: `Transfers.start_all`),
    i2c-designware one address only.
    """

    reads_inside: bool = False
    many_addresses: bool = False

    @classmethod
    def of(cls, adapter: str | None) -> Shapes:
        """The shapes an adapter of `ADAPTER_RULES` takes; None (unknown): the narrowest."""
        if adapter is None:
            return cls()
        rules = ADAPTER_RULES[adapter]
        return cls(reads_inside=not rules.reads_last_only, many_addresses=not rules.one_address)

    @property
    def pairs_per_transfer(self) -> int:
        return CHIPS_PER_TRANSFER if self.reads_inside and self.many_addresses else 1

    def describe(self) -> str:
        if self.pairs_per_transfer > 1:
            return f"(write, read) pairs of up to {self.pairs_per_transfer} chips in one ioctl"
        if self.many_addresses:
            return "one chip's (write, read) an ioctl (writes to many chips then one read taken; reads last only)"
        return "one chip an ioctl"


#: Bits of one command on the wire: start, address, command byte; then repeated
#: start, address, status byte (SM), or status and six data bytes (RM of X, Y, Z).
SM_BITS = (1 + BITS_PER_BYTE * 2) + (1 + BITS_PER_BYTE * 2)
RM_BITS = (1 + BITS_PER_BYTE * 2) + (1 + BITS_PER_BYTE * 8)
#: RR: write the command and the address byte, read status and two data bytes.
RR_BITS = (1 + BITS_PER_BYTE * 3) + (1 + BITS_PER_BYTE * 4)


@dataclass(frozen=True)
class CycleBound:
    """The fastest cycle of a scheduler, and where its time goes (s)."""

    scheduler: str
    n_chips: int
    bus_hz: float
    start_s: float  # SM transfers (0 for burst)
    wait_s: float  # waiting for conversions that the bus cannot hide
    read_s: float  # RM transfers
    check_s: float = 0.0  # reading one chip's registers back (and EX/SB around it in burst)
    ioctls: int = 0  # ioctls of the slowest cycle
    overhead_s: float = 0.0  # the fixed cost of each
    adapter: str | None = None  # whose rules were counted (None: unknown, the narrowest)

    @property
    def cycle_s(self) -> float:
        return self.start_s + self.wait_s + self.read_s + self.check_s

    @property
    def rate_hz(self) -> float:
        return 1.0 / self.cycle_s

    def describe(self) -> str:
        return (
            f"{self.scheduler}: {self.rate_hz:.1f} Hz at most ({self.cycle_s * 1e3:.2f} ms a cycle: "
            f"start {self.start_s * 1e3:.2f}, wait {self.wait_s * 1e3:.2f}, read {self.read_s * 1e3:.2f}, "
            f"check {self.check_s * 1e3:.2f} ms) for {self.n_chips} chips on a {self.bus_hz / 1e3:g} kHz bus, "
            f"{self.ioctls} ioctls of {self.overhead_s * 1e6:.0f} us ({self.adapter or 'unknown adapter'})"
        )


def _transfers_s(
    n_chips: int, bits_per_chip: int, per_transfer: int, bus_hz: float, overhead_s: float
) -> tuple[float, int]:
    """Time (s) and ioctls of ``n_chips`` commands, ``per_transfer`` chips an ioctl
    (one stop bit and one fixed cost each)."""
    transfers = math.ceil(n_chips / per_transfer)
    return (n_chips * bits_per_chip + transfers) / bus_hz + transfers * overhead_s, transfers


def cycle_bound(
    scheduler: str,
    n_chips: int,
    settings: mlx.Settings,
    bus_hz: float,
    overhead_s: float = 0.0,
    readback: bool = True,
    temperature: bool = False,
    adapter: str | None = "permissive",
) -> CycleBound:
    """The fastest cycle for ``n_chips`` at ``settings`` on a ``bus_hz`` bus.

    ``bus_hz`` is the clock the wire really runs at, when it is known.
    ``overhead_s`` is the fixed cost of one ioctl (kernel and adapter), which
    the wire time does not include; measure it on the board (`acquire.board`).
    ``adapter`` (`ADAPTER_RULES`; None: unknown, counted as the narrowest)
    decides how many ioctls a cycle takes (`Shapes`). ``readback`` counts the
    cycle that also reads one chip's three registers back (six with TCMP_EN); ``temperature`` the
    cycle that also converts and reads T (a burst then converts T every time): the
    bound is that of the slowest cycle, which every cycle must fit.
    """
    shapes = Shapes.of(adapter)
    zyxt = mlx.ZYXT_XYZT if temperature else mlx.ZYXT_XYZ
    conversion = settings.single_measurement_us(zyxt) * 1e-6 * OSC_MARGIN
    rm_bits = rm_bits_for(zyxt)
    sm_one = (SM_BITS + 1) / bus_hz + overhead_s
    rm_one = (rm_bits + 1) / bus_hz + overhead_s
    # RR of CONF1..CONF3, and of OFFSET_X/Y/Z with TCMP_EN (`MLX90393.configuration_matches`).
    n_rr = 6 if settings.tcmp_en else 3
    checks = (n_rr + (2 if scheduler == "burst" else 0)) if readback else 0  # (EX before, SB after in burst)
    check = n_rr * ((RR_BITS + 1) / bus_hz + overhead_s) if readback else 0.0

    def bound(start: float, wait: float, read: float, check: float, ioctls: int) -> CycleBound:
        return CycleBound(
            scheduler, n_chips, bus_hz, start, wait, read, check, ioctls + checks, overhead_s, adapter
        )

    if scheduler == "naive":
        return bound(n_chips * sm_one, n_chips * conversion, n_chips * rm_one, check, 2 * n_chips)
    read, read_ioctls = _transfers_s(n_chips, rm_bits, shapes.pairs_per_transfer, bus_hz, overhead_s)
    if scheduler == "overlapped":
        # The chip read back is left out of the SM transfer, read back while the others
        # convert, started then (SM with its status read) and read last (`Reader`).
        n_sm = n_chips - 1 if readback else n_chips
        # Every SM with its status read (`Transfers.start_all`): chip k's SM ends k SMs
        # into the transfers, its RM comes k RMs after the first, and an RM is longer,
        # so waiting for the first chip's conversion is enough for all.
        start, start_ioctls = (
            _transfers_s(n_sm, SM_BITS, shapes.pairs_per_transfer, bus_hz, overhead_s) if n_sm else (0.0, 0)
        )
        first = overhead_s + (1 + BITS_PER_BYTE * 2) / bus_hz
        rm_at = overlapped_rm_at(
            first + conversion,
            start + check,
            conversion,
            first,
            last_offset_s(n_chips, rm_bits, shapes.pairs_per_transfer, bus_hz, overhead_s)
            if readback
            else None,
            sm_one if readback else 0.0,
        )
        if readback:
            start += sm_one
            start_ioctls += 1
        return bound(start, rm_at - start - check, read, check, start_ioctls + read_ioctls)
    if scheduler == "burst":
        interval = _burst_interval_s(settings, zyxt)
        if readback:
            check += 2 * sm_one  # EX before the registers (refused in burst), SB after
        return bound(0.0, max(0.0, interval - read), read, check, read_ioctls)
    raise ConfigError(f"scheduler: expected one of {', '.join(SCHEDULERS)}, got {scheduler!r}")


def overlapped_rm_at(
    first_ready: float,
    checked: float,
    conversion: float,
    first: float,
    last_offset: float | None,
    sm_one: float,
) -> float:
    """When the RM transfers of an overlapped cycle may begin (s from the cycle's start).

    Not before the first chip's conversion is done (``first_ready``: its SM's ioctl
    cost and command, then the conversion). With a chip read back (``last_offset``
    not None: when, into the RM transfers, the last chip's RM command reaches it):
    not before that chip's SM, sent at ``checked``, is over (``sm_one``), nor so early
    that its RM, read last, comes before its conversion is done.
    """
    if last_offset is None:
        return max(first_ready, checked)
    return max(first_ready, checked + sm_one, checked + first + conversion - last_offset + READY_GUARD_S)


def rm_bits_for(zyxt: int) -> int:
    """Bits on the wire of one chip's RM of ``zyxt`` (X, Y, Z; T adds a word)."""
    return RM_BITS + (BITS_PER_BYTE * 2 if zyxt & mlx.ZYXT_T else 0)


def last_offset_s(n_chips: int, rm_bits: int, per_transfer: int, bus_hz: float, overhead_s: float) -> float:
    """How long after the RM transfers begin the last chip's RM command reaches it (s)."""
    transfers, k = divmod(n_chips - 1, per_transfer)
    full = (per_transfer * rm_bits + 1) / bus_hz + overhead_s
    return transfers * full + overhead_s + (k * rm_bits + 1 + BITS_PER_BYTE * 2) / bus_hz


def burst_readback_stays_fresh(
    bound: CycleBound, settings: mlx.Settings, rate_hz: float, temperature: bool = False
) -> bool:
    """Whether reading a chip's registers back in burst mode (EX, RR, SB, which restart
    its burst) leaves it time for a new result before the next cycle reads it: a period
    of at least a whole cycle plus one burst interval. The read-back follows the publish
    and the chip is read last in the next cycle (`Reader.upkeep`) while the host's work
    between the RM and the read-back takes less than the other chips' RM transfers (4.7
    ms for 16 chips on a Pi 4's adapter at 400 kHz); beyond, the read-back comes right
    after the RM (`Reader.read`). Either way this suffices. ``temperature``: the burst
    converts T too."""
    return 1.0 / rate_hz >= bound.cycle_s + _burst_interval_s(
        settings, mlx.ZYXT_XYZT if temperature else mlx.ZYXT_XYZ
    )


def _burst_interval_s(settings: mlx.Settings, zyxt: int = mlx.ZYXT_XYZ) -> float:
    """The longest interval between a chip's burst results (``zyxt``), s: the oscillator's margin included."""
    return settings.burst_interval_us(zyxt) * 1e-6 * OSC_MARGIN
