"""How fast each scheduler can read every chip: the computed cycle bound.

`cycle_bound` computes the fastest cycle each can achieve from the chip
settings and the bus clock (docs/performance.md has the figures), so the daemon can refuse a rate it cannot meet.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..chip import mlx90393 as mlx
from ..chip.i2c import BITS_PER_BYTE, I2C_RDWR_MAX_MSGS
from ..errors import ConfigError

SCHEDULERS = ("naive", "overlapped", "burst")
#: The chip's oscillator runs within +-20 % of nominal: wait for the slowest.
OSC_MARGIN = 1.2
#: Chips per transfer: two messages each, at most 42 messages an ioctl.
CHIPS_PER_TRANSFER = I2C_RDWR_MAX_MSGS // 2
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

    @property
    def cycle_s(self) -> float:
        return self.start_s + self.wait_s + self.read_s + self.check_s

    @property
    def rate_hz(self) -> float:
        return 1.0 / self.cycle_s

    def describe(self) -> str:
        return (f"{self.scheduler}: {self.rate_hz:.1f} Hz at most ({self.cycle_s * 1e3:.2f} ms a cycle: "
                f"start {self.start_s * 1e3:.2f}, wait {self.wait_s * 1e3:.2f}, read {self.read_s * 1e3:.2f}, "
                f"check {self.check_s * 1e3:.2f} ms) for {self.n_chips} chips on a {self.bus_hz / 1e3:g} kHz bus")


def _batched_s(n_chips: int, bits_per_chip: int, bus_hz: float, overhead_s: float) -> float:
    transfers = math.ceil(n_chips / CHIPS_PER_TRANSFER)
    return (n_chips * bits_per_chip + transfers) / bus_hz + transfers * overhead_s


def cycle_bound(scheduler: str, n_chips: int, settings: mlx.Settings, bus_hz: float,
                overhead_s: float = 0.0, readback: bool = True, temperature: bool = False) -> CycleBound:
    """The fastest cycle for ``n_chips`` at ``settings`` on a ``bus_hz`` bus.

    ``overhead_s`` is the fixed cost of one ioctl (kernel and adapter), which
    the wire time does not include; measure it on the board. ``readback``
    counts the cycle that also reads one chip's three registers back;
    ``temperature`` the cycle that also converts and reads T (not in burst):
    the bound is that of the slowest cycle, which every cycle must fit.
    """
    zyxt = mlx.ZYXT_XYZT if temperature and scheduler != "burst" else mlx.ZYXT_XYZ
    conversion = settings.single_measurement_us(zyxt) * 1e-6 * OSC_MARGIN
    rm_bits = RM_BITS + (BITS_PER_BYTE * 2 if zyxt & mlx.ZYXT_T else 0)
    sm_one = (SM_BITS + 1) / bus_hz + overhead_s
    rm_one = (rm_bits + 1) / bus_hz + overhead_s
    check = 3 * ((RR_BITS + 1) / bus_hz + overhead_s) if readback else 0.0
    if scheduler == "naive":
        return CycleBound(scheduler, n_chips, bus_hz, n_chips * sm_one, n_chips * conversion, n_chips * rm_one,
                          check)
    read = _batched_s(n_chips, rm_bits, bus_hz, overhead_s)
    if scheduler == "overlapped":
        start = _batched_s(n_chips, SM_BITS, bus_hz, overhead_s)
        # The first chip's conversion starts one command into the SM transfer; the RM
        # transfer may begin once it is done (later chips finish as their RMs arrive).
        first = (1 + BITS_PER_BYTE * 2) / bus_hz
        return CycleBound(scheduler, n_chips, bus_hz, start, max(0.0, first + conversion - start), read, check)
    if scheduler == "burst":
        interval = _burst_interval_s(settings)
        if readback:
            check += 2 * sm_one  # EX before the registers (refused in burst), SB after
        return CycleBound(scheduler, n_chips, bus_hz, 0.0, max(0.0, interval - read), read, check)
    raise ConfigError(f"scheduler: expected one of {', '.join(SCHEDULERS)}, got {scheduler!r}")


def burst_readback_stays_fresh(bound: CycleBound, settings: mlx.Settings, rate_hz: float) -> bool:
    """Whether reading a chip's registers back in burst mode (EX, RR, SB, which restart
    its burst) leaves it time for a new result before the next cycle reads it: a period
    of at least a whole cycle plus one burst interval (conservative: the chip read back
    is read again later than the cycle's start)."""
    return 1.0 / rate_hz >= bound.cycle_s + _burst_interval_s(settings)


def _burst_interval_s(settings: mlx.Settings) -> float:
    """The longest interval between a chip's burst results (X, Y, Z), s: the oscillator's margin included."""
    return settings.burst_interval_us(mlx.ZYXT_XYZ) * 1e-6 * OSC_MARGIN
