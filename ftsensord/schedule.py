"""Scheduling the bus: how a cycle reads every chip, and how fast it can.

Three strategies (docs/performance.md has the figures):

- ``naive``: for each chip in turn, SM, wait for its conversion, RM.
- ``overlapped``: SM to every chip in one transfer, wait for the conversions
  (which run in parallel), RM every chip in one transfer.
- ``burst``: the chips convert on their own clock (SB once); a cycle is one
  RM transfer. The bus itself is then the limit.

`cycle_bound` computes the fastest cycle each can achieve from the chip
settings and the bus clock, so the daemon can refuse a rate it cannot meet.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from . import mlx90393 as mlx
from .bus import BITS_PER_BYTE, I2C_RDWR_MAX_MSGS, Bus
from .driver import MLX90393, Measurement
from .errors import ChipError, ConfigError

SCHEDULERS = ("naive", "overlapped", "burst")
#: The chip's oscillator runs within +-20 % of nominal: wait for the slowest.
OSC_MARGIN = 1.2
#: Chips per transfer: two messages each, at most 42 messages an ioctl.
CHIPS_PER_TRANSFER = I2C_RDWR_MAX_MSGS // 2
#: Bits of one command on the wire: start, address, command byte; then repeated
#: start, address, status byte (SM), or status and six data bytes (RM of X, Y, Z).
SM_BITS = (1 + BITS_PER_BYTE * 2) + (1 + BITS_PER_BYTE * 2)
RM_BITS = (1 + BITS_PER_BYTE * 2) + (1 + BITS_PER_BYTE * 8)


@dataclass(frozen=True)
class CycleBound:
    """The fastest cycle of a scheduler, and where its time goes (s)."""

    scheduler: str
    n_chips: int
    bus_hz: float
    start_s: float  # SM transfers (0 for burst)
    wait_s: float  # waiting for conversions that the bus cannot hide
    read_s: float  # RM transfers

    @property
    def cycle_s(self) -> float:
        return self.start_s + self.wait_s + self.read_s

    @property
    def rate_hz(self) -> float:
        return 1.0 / self.cycle_s

    def describe(self) -> str:
        return (f"{self.scheduler}: {self.rate_hz:.1f} Hz at most ({self.cycle_s * 1e3:.2f} ms a cycle: "
                f"start {self.start_s * 1e3:.2f}, wait {self.wait_s * 1e3:.2f}, read {self.read_s * 1e3:.2f} ms) "
                f"for {self.n_chips} chips on a {self.bus_hz / 1e3:g} kHz bus")


def _batched_s(n_chips: int, bits_per_chip: int, bus_hz: float, overhead_s: float) -> float:
    transfers = math.ceil(n_chips / CHIPS_PER_TRANSFER)
    return (n_chips * bits_per_chip + transfers) / bus_hz + transfers * overhead_s


def cycle_bound(scheduler: str, n_chips: int, settings: mlx.Settings, bus_hz: float,
                overhead_s: float = 0.0) -> CycleBound:
    """The fastest cycle for ``n_chips`` at ``settings`` on a ``bus_hz`` bus.

    ``overhead_s`` is the fixed cost of one ioctl (kernel and adapter), which
    the wire time does not include; measure it on the board.
    """
    conversion = settings.single_measurement_us(mlx.ZYXT_XYZ) * 1e-6 * OSC_MARGIN
    sm_one = (SM_BITS + 1) / bus_hz + overhead_s
    rm_one = (RM_BITS + 1) / bus_hz + overhead_s
    if scheduler == "naive":
        return CycleBound(scheduler, n_chips, bus_hz, n_chips * sm_one, n_chips * conversion, n_chips * rm_one)
    read = _batched_s(n_chips, RM_BITS, bus_hz, overhead_s)
    if scheduler == "overlapped":
        start = _batched_s(n_chips, SM_BITS, bus_hz, overhead_s)
        # The first chip's conversion starts one command into the SM transfer; the RM
        # transfer may begin once it is done (later chips finish as their RMs arrive).
        first = (1 + BITS_PER_BYTE * 2) / bus_hz
        return CycleBound(scheduler, n_chips, bus_hz, start, max(0.0, first + conversion - start), read)
    if scheduler == "burst":
        interval = settings.burst_interval_us(mlx.ZYXT_XYZ) * 1e-6 * OSC_MARGIN
        return CycleBound(scheduler, n_chips, bus_hz, 0.0, max(0.0, interval - read), read)
    raise ConfigError(f"scheduler: expected one of {', '.join(SCHEDULERS)}, got {scheduler!r}")


@dataclass
class ChipResult:
    """What one cycle got from one chip: a measurement, or why not."""

    address: int
    measurement: Measurement | None = None
    error: ChipError | None = None

    @property
    def ok(self) -> bool:
        return self.measurement is not None


@dataclass
class Reader:
    """Reads every chip once a cycle with one of the `SCHEDULERS`.

    Healthy chips share batched transfers. A NACK aborts a whole transfer, so
    when a batch fails its chips are tried one by one; a chip that failed is
    then read on its own until it answers again, so it cannot cost the others
    their data.
    """

    bus: Bus
    chips: list[MLX90393]
    scheduler: str
    settings: mlx.Settings
    bus_hz: float = 400e3
    overhead_s: float = 0.0
    failing: set[int] = field(default_factory=set)

    def __post_init__(self) -> None:
        if self.scheduler not in SCHEDULERS:
            raise ConfigError(f"scheduler: expected one of {', '.join(SCHEDULERS)}, got {self.scheduler!r}")

    def conversion_s(self, zyxt: int) -> float:
        return self.settings.single_measurement_us(zyxt) * 1e-6 * OSC_MARGIN

    def start(self) -> dict[int, ChipError]:
        """Reset and configure every chip (and start burst mode); returns the failures."""
        errors = {}
        for chip in self.chips:
            try:
                chip.reset()
                chip.configure(self.settings)
                if self.scheduler == "burst":
                    chip.start_burst(mlx.ZYXT_XYZ)
            except ChipError as exc:
                errors[chip.address] = exc
                self.failing.add(chip.address)
        return errors

    def stop(self) -> None:
        """Put every chip back to idle (EX), ignoring the ones that do not answer."""
        for chip in self.chips:
            try:
                chip.exit_mode()
            except ChipError:
                pass

    def read(self, zyxt: int = mlx.ZYXT_XYZ) -> list[ChipResult]:
        """One cycle: a result for every chip, in the order of ``chips``.

        ``zyxt`` picks the items (add T now and then for the temperature); burst
        mode reads what it was started with, X, Y and Z.
        """
        if self.scheduler == "burst":
            zyxt = mlx.ZYXT_XYZ
        if self.scheduler == "naive":
            results = {c.address: self._single(c, zyxt) for c in self.chips}
        else:
            results = {}
            ready = self.chips
            if self.scheduler == "overlapped":
                t0 = self.bus.monotonic()
                started = self._batch(self.chips, lambda c: c.sm_messages(zyxt), self._decode_sm)
                results = {a: ChipResult(a, error=e) for a, e in started.items() if isinstance(e, ChipError)}
                ready = [c for c in self.chips if c.address not in results]
                # Chip k's RM reaches it later after its SM than chip 0's does (an RM
                # is longer than an SM), so waiting for chip 0 is enough (docs/performance.md).
                first = self.overhead_s + (1 + BITS_PER_BYTE * 2) / self.bus_hz
                self.bus.sleep(max(0.0, t0 + first + self.conversion_s(zyxt) - self.bus.monotonic()))
            decoded = self._batch(ready, lambda c: c.rm_messages(zyxt), lambda c, r: c.decode_measurement(r, zyxt))
            for a, v in decoded.items():
                results[a] = ChipResult(a, error=v) if isinstance(v, ChipError) else ChipResult(a, v)
        for address, r in results.items():
            (self.failing.discard if r.ok else self.failing.add)(address)
        return [results[c.address] for c in self.chips]

    @staticmethod
    def _decode_sm(chip: MLX90393, reply: bytes) -> None:
        status = mlx.Status(reply[0])
        if status.error and status.sm_mode:
            return  # it got the SM before its batch failed, and is converting
        chip.decode_sm(reply)

    def _single(self, chip: MLX90393, zyxt: int) -> ChipResult:
        try:
            chip.start_single(zyxt)
            self.bus.sleep(self.conversion_s(zyxt))
            return ChipResult(chip.address, chip.read_measurement(zyxt))
        except ChipError as exc:
            return ChipResult(chip.address, error=exc)

    def _batch(self, chips: list[MLX90393], messages: Callable, decode: Callable) -> dict[int, Any]:
        """One transfer for the healthy chips (21 to an ioctl), one each for the rest.

        Returns per address what ``decode(chip, reply)`` gave, or the `ChipError`.
        """
        out: dict[int, Any] = {}
        healthy = [c for c in chips if c.address not in self.failing]
        alone = [c for c in chips if c.address in self.failing]
        for k in range(0, len(healthy), CHIPS_PER_TRANSFER):
            group = healthy[k:k + CHIPS_PER_TRANSFER]
            pairs = [messages(c) for c in group]
            try:
                self.bus.i2c_rdwr(*[m for pair in pairs for m in pair])
            except OSError:
                alone.extend(group)  # which one failed? ask each on its own
                continue
            for chip, (_, read) in zip(group, pairs):
                out[chip.address] = _decoded(decode, chip, bytes(read))
        for chip in alone:
            write, read = messages(chip)
            try:
                out[chip.address] = _decoded(decode, chip, chip.transfer(bytes(write), len(read)))
            except ChipError as exc:
                out[chip.address] = exc
        return out


def _decoded(decode: Callable, chip: MLX90393, reply: bytes) -> Any:
    try:
        return decode(chip, reply)
    except ChipError as exc:
        return exc
