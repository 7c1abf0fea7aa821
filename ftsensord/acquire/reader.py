"""Reading every chip once a cycle: the three schedulers and their batched transfers.

- ``naive``: for each chip in turn, SM, wait for its conversion, RM.
- ``overlapped``: SM to every chip in one transfer, wait for the conversions
  (which run in parallel), RM every chip in one transfer.
- ``burst``: the chips convert on their own clock (SB once); a cycle is one
  RM transfer. The bus itself is then the limit.

How fast each can go is `bound.cycle_bound`; which chips to trust and how a
failing one comes back is `health.ChipCare`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from ..chip import mlx90393 as mlx
from ..chip.driver import MLX90393
from ..chip.i2c import BITS_PER_BYTE, Bus
from ..errors import ChipError, ConfigError
from .bound import CHIPS_PER_TRANSFER, OSC_MARGIN, SCHEDULERS
from .health import ChipCare, ChipHealth, ChipResult


@dataclass
class Reader:
    """Reads every chip once a cycle with one of the `SCHEDULERS`, and keeps them healthy.

    Healthy chips share batched transfers. A NACK aborts a whole transfer, so
    when a batch fails its chips are tried one by one. Failing chips are left
    to `ChipCare`, which brings them back. Every ``readback_every`` cycles one
    chip's configuration is read back and compared (round robin: with 16 chips,
    each every 16 cycles at the default of 1).
    """

    bus: Bus
    chips: list[MLX90393]
    scheduler: str
    settings: mlx.Settings
    bus_hz: float = 400e3
    overhead_s: float = 0.0
    stuck_cycles: int | None = None  # None: `health.stuck_cycles_for` the settings
    readback_every: int = 1
    care: ChipCare = field(init=False)
    cycle: int = 0

    def __post_init__(self) -> None:
        if self.scheduler not in SCHEDULERS:
            raise ConfigError(f"scheduler: expected one of {', '.join(SCHEDULERS)}, got {self.scheduler!r}")
        self.care = ChipCare(self.bus, self.chips, self.settings, burst=self.scheduler == "burst",
                             stuck_cycles=self.stuck_cycles)

    @property
    def health(self) -> dict[int, ChipHealth]:
        return self.care.health

    @property
    def failing(self) -> set[int]:
        return self.care.failing

    def conversion_s(self, zyxt: int) -> float:
        return self.settings.single_measurement_us(zyxt) * 1e-6 * OSC_MARGIN

    def start(self) -> dict[int, ChipError]:
        """Reset and configure every chip (and start burst mode); returns the failures."""
        errors = {}
        for chip in self.chips:
            try:
                self.care.initialise(chip)
            except ChipError as exc:
                errors[chip.address] = exc
                self.care.fail(chip.address, self.bus.monotonic())
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
        now = self.bus.monotonic()
        healthy = [c for c in self.chips if not self.health[c.address].failing]
        self.care.new_cycle()
        # The longest-failing first: every chip gets its turn.
        due = sorted((c for c in self.chips if self.health[c.address].failing),
                     key=lambda c: self.health[c.address].retry_at)
        results = {c.address: self.care.recover(c, now) for c in due}
        if self.scheduler == "naive":
            results.update({c.address: self._single(c, zyxt) for c in healthy})
        else:
            ready = healthy
            if self.scheduler == "overlapped":
                t0 = self.bus.monotonic()
                started = self._batch(healthy, lambda c: c.sm_messages(zyxt), self._decode_sm)
                results.update({a: ChipResult(a, error=e) for a, e in started.items() if isinstance(e, ChipError)})
                ready = [c for c in healthy if c.address not in results]
                # Chip k's RM reaches it later after its SM than chip 0's does (an RM
                # is longer than an SM), so waiting for chip 0 is enough (docs/performance.md).
                first = self.overhead_s + (1 + BITS_PER_BYTE * 2) / self.bus_hz
                self.bus.sleep(max(0.0, t0 + first + self.conversion_s(zyxt) - self.bus.monotonic()))
            decoded = self._batch(ready, lambda c: c.rm_messages(zyxt), lambda c, r: c.decode_measurement(r, zyxt))
            for a, v in decoded.items():
                results[a] = ChipResult(a, error=v) if isinstance(v, ChipError) else ChipResult(a, v)
        for chip in healthy:
            results[chip.address] = self.care.judge(results[chip.address], now)
        if self.readback_every and self.cycle % self.readback_every == 0 and healthy:
            self.care.read_back(healthy[(self.cycle // self.readback_every) % len(healthy)], now)
        self.cycle += 1
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
        """One transfer per 21 chips; when one fails, each of its chips on its own.

        Returns per address what ``decode(chip, reply)`` gave, or the `ChipError`.
        """
        out: dict[int, Any] = {}
        alone: list[MLX90393] = []
        for k in range(0, len(chips), CHIPS_PER_TRANSFER):
            group = chips[k:k + CHIPS_PER_TRANSFER]
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
