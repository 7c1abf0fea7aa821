"""Reading every chip once a cycle: the three schedulers and their batched transfers.

- ``naive``: for each chip in turn, SM, wait for its conversion, RM.
- ``overlapped``: SM to every chip in one transfer, wait for the conversions
  (which run in parallel), RM every chip in one transfer. The chip whose
  registers are read back this cycle is read back during the wait, then
  started, and read last.
- ``burst``: the chips convert on their own clock (SB once); a cycle is one
  RM transfer. The bus itself is then the limit.

"One transfer" is as wide as the adapter allows (`bound.Shapes`), learnt by
`probe_shapes` at start and again after a refusal, so a refused ioctl is paid
once, not every cycle. How fast each can go is `bound.cycle_bound`; which
chips to trust and how a failing one comes back is `health.ChipCare`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from smbus2 import i2c_msg

from ..chip import mlx90393 as mlx
from ..chip.driver import MLX90393
from ..chip.i2c import BITS_PER_BYTE, I2C_RDWR_MAX_MSGS, SHAPE_REFUSED, Bus
from ..errors import ChipError, ChipProtocolError, ChipRefusedError, ConfigError
from .bound import OSC_MARGIN, SCHEDULERS, Shapes, overlapped_rm_at
from .health import ChipCare, ChipHealth, ChipResult

log = logging.getLogger("ftsensord")


def _rr_tref(chip: MLX90393) -> tuple[i2c_msg, i2c_msg]:
    # RR of TREF: harmless in every mode (refused in burst mode, which changes nothing).
    return chip.messages(bytes([mlx.CMD_RR, mlx.REG_TREF << 2]), 3)


def _accepted(bus: Bus, msgs: list[i2c_msg]) -> bool | None:
    """True: the adapter took the transfer; False: it refused its shape; None: no answer (NACK, I/O)."""
    try:
        bus.i2c_rdwr(*msgs)
    except OSError as exc:
        return False if exc.errno in SHAPE_REFUSED else None
    return True


def probe_shapes(bus: Bus, chips: list[MLX90393], tries: int = 4) -> Shapes | None:
    """What the adapter takes in one ioctl, asked with harmless register reads.

    A chip that answers a plain (write, read) is asked two pairs in one ioctl
    (a read that is not last: i2c-bcm2835 refuses), then with a second chip
    that answers, a write to each and one read (two addresses: i2c-designware
    refuses). EOPNOTSUPP and EINVAL mean "not this shape"; a NACK or I/O error
    says nothing, and the next chip is tried (at most ``tries``). None when no
    chip answered at all.
    """
    answering = [c for c in chips[:tries] if _accepted(bus, list(_rr_tref(c)))]
    if not answering:
        return None
    a = answering[0]
    reads_inside = _accepted(bus, [*_rr_tref(a), *_rr_tref(a)]) is True
    many = False
    for b in answering[1:]:
        took = _accepted(bus, [_rr_tref(a)[0], *_rr_tref(b)])
        if took is not None:
            many = took
            break
    return Shapes(reads_inside=reads_inside, many_addresses=many)


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
    xfer: Transfers = field(init=False)

    def __post_init__(self) -> None:
        if self.scheduler not in SCHEDULERS:
            raise ConfigError(f"scheduler: expected one of {', '.join(SCHEDULERS)}, got {self.scheduler!r}")
        self.care = ChipCare(self.bus, self.chips, self.settings, burst=self.scheduler == "burst",
                             stuck_cycles=self.stuck_cycles)
        self.xfer = Transfers(self.bus)
        # What the bus knows of itself (a simulated one, or a board measured by
        # `acquire.board`) beats the configured figures in the wait it times.
        timing = getattr(self.bus, "timing", None)
        if timing is not None and timing.clock_hz:
            self.bus_hz = timing.clock_hz
        if timing is not None and timing.ioctl_s is not None and timing.clock_hz:
            self.overhead_s = timing.ioctl_s

    @property
    def shapes(self) -> Shapes:
        """What the adapter takes in one ioctl, as learnt."""
        return self.xfer.shapes

    def _learn_shapes(self) -> None:
        self.xfer.learn([c for c in self.chips if not self.health[c.address].failing] or self.chips, self.cycle)

    @property
    def health(self) -> dict[int, ChipHealth]:
        return self.care.health

    @property
    def failing(self) -> set[int]:
        return self.care.failing

    def conversion_s(self, zyxt: int) -> float:
        return self.settings.single_measurement_us(zyxt) * 1e-6 * OSC_MARGIN

    def start(self) -> dict[int, ChipError]:
        """Learn what the adapter takes, reset and configure every chip (and start
        burst mode); returns the failures."""
        self._learn_shapes()
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
        if self.xfer.reprobe:
            self._learn_shapes()
        now = self.bus.monotonic()
        healthy = [c for c in self.chips if not self.health[c.address].failing]
        self.care.new_cycle()
        # The longest-failing first: every chip gets its turn.
        due = sorted((c for c in self.chips if self.health[c.address].failing),
                     key=lambda c: self.health[c.address].retry_at)
        results = {c.address: self.care.recover(c, now) for c in due}
        checked = None
        if self.readback_every and self.cycle % self.readback_every == 0 and healthy:
            checked = healthy[(self.cycle // self.readback_every) % len(healthy)]
        if self.scheduler == "naive":
            results.update({c.address: self._single(c, zyxt) for c in healthy})
        elif self.scheduler == "overlapped":
            results.update(self._overlapped(healthy, zyxt, checked, now))
            checked = None  # read back during the wait
        else:
            results.update(self.xfer.read_all(healthy, zyxt))
        for chip in healthy:
            if chip.address in results and not self.health[chip.address].failing:
                results[chip.address] = self.care.judge(results[chip.address], now)
        if checked is not None:
            self.care.read_back(checked, now)
        self.cycle += 1
        return [results[c.address] for c in self.chips]

    def _overlapped(self, healthy: list[MLX90393], zyxt: int, checked: MLX90393 | None,
                    now: float) -> dict[int, ChipResult]:
        """SM every chip, wait, RM every chip; ``checked`` is read back while the others
        convert, then started and read last (`bound.cycle_bound` counts the same)."""
        results: dict[int, ChipResult] = {}
        self.xfer.unread_sm.clear()
        t0 = self.bus.monotonic()
        others = [c for c in healthy if c is not checked]
        results.update(self.xfer.start_all(others, zyxt))
        first = self.overhead_s + (1 + BITS_PER_BYTE * 2) / self.bus_hz
        conversion = self.conversion_s(zyxt)
        ready = [c for c in others if c.address not in results]
        last_offset, sm_one = None, 0.0
        if checked is not None:
            self.care.read_back(checked, now)
            if self.health[checked.address].failing:
                results[checked.address] = ChipResult(checked.address, error=ChipProtocolError(
                    checked.address, "its registers read back differ from what was written: re-initialising"))
            else:
                t_sm = self.bus.monotonic()
                results.update(self.xfer.start_all([checked], zyxt))
                if checked.address not in results:
                    ready.append(checked)
                    n = len(ready)
                    per = self.shapes.pairs_per_transfer
                    rm_bits = (1 + BITS_PER_BYTE * 2) + (1 + BITS_PER_BYTE * (1 + 2 * len(mlx.zyxt_items(zyxt))))
                    transfers, k = divmod(n - 1, per)
                    last_offset = (transfers * ((per * rm_bits + 1) / self.bus_hz + self.overhead_s)
                                   + self.overhead_s + (k * rm_bits + 1 + BITS_PER_BYTE * 2) / self.bus_hz)
                    sm_one = self.bus.monotonic() - t_sm
                    # Measured from the cycle's start, as the bound computes it.
                    rm_at = overlapped_rm_at(first + conversion, t_sm - t0, conversion, first, last_offset, sm_one)
                    self.bus.sleep(max(0.0, t0 + rm_at - self.bus.monotonic()))
        if last_offset is None:
            self.bus.sleep(max(0.0, t0 + first + conversion - self.bus.monotonic()))
        read = self.xfer.read_all(ready, zyxt)
        for a, r in read.items():
            if a in self.xfer.unread_sm and isinstance(r.error, ChipRefusedError) and r.error.command == "RM" \
                    and not r.error.status.sm_mode:  # type: ignore[attr-defined]
                # No data and no conversion under way: its SM, sent as a write alone, was
                # refused. A failure now, not a stale result (`health.STALE_LIMIT`).
                read[a] = ChipResult(a, error=ChipRefusedError(
                    a, f"SM refused (seen through RM, status {r.error.status}: no conversion under way)",
                    r.error.status, "SM"))
        results.update(read)
        return results

    def _single(self, chip: MLX90393, zyxt: int) -> ChipResult:
        try:
            chip.start_single(zyxt)
            self.bus.sleep(self.conversion_s(zyxt))
            return ChipResult(chip.address, chip.read_measurement(zyxt))
        except ChipError as exc:
            return ChipResult(chip.address, error=exc)


class Transfers:
    """The transfers of one bus as wide as its adapter takes (`Shapes`), learnt by
    `probe_shapes` at start and again after a refusal, so a refused ioctl is paid
    once, not every cycle. ``unread_sm``: chips whose last SM went without its status read."""

    def __init__(self, bus: Bus):
        self.bus = bus
        self.shapes = Shapes()  # the narrowest until `learn` has asked
        self.reprobe = True
        self.probe_at = 0  # the cycle of the next probe while none has answered
        self.unread_sm: set[int] = set()

    def learn(self, chips: list[MLX90393], cycle: int) -> None:
        if cycle < self.probe_at:
            return
        found = probe_shapes(self.bus, chips)
        if found is not None:
            self.shapes, self.reprobe = found, False
        else:  # no chip answered: the narrowest meanwhile, asked again in 100 cycles (1 s at 100 Hz)
            self.probe_at = cycle + 100

    def start_all(self, chips: list[MLX90393], zyxt: int) -> dict[int, ChipResult]:
        """SM to ``chips``; the refusals (a chip missing from the result started).

        Where the adapter takes many writes but one read (i2c-bcm2835), the SMs go
        as writes alone, up to 42 chips an ioctl, and their status is not read: a
        chip that refused its SM (a stray mode, lost registers) shows it in the
        following RM, refused for lack of new data while its status shows no
        conversion under way (SM_MODE clear): `_overlapped` turns that into the SM's
        refusal, so the chip fails at once as if the SM's status had been read.
        What is lost is only the reply's byte itself (never compared whole anyway).
        """
        if len(chips) > 1 and self.shapes.sm_writes_only:
            alone: list[MLX90393] = []
            for k in range(0, len(chips), I2C_RDWR_MAX_MSGS):
                group = chips[k:k + I2C_RDWR_MAX_MSGS]
                try:
                    self.bus.i2c_rdwr(*[c.sm_messages(zyxt)[0] for c in group])
                except OSError as exc:
                    self.refused(exc)
                    alone.extend(group)  # which one failed? ask each with its status
                    continue
                self.unread_sm.update(c.address for c in group)
            started = self.batch(alone, lambda c: c.sm_messages(zyxt), self._decode_sm)
        else:
            started = self.batch(chips, lambda c: c.sm_messages(zyxt), self._decode_sm)
        return {a: ChipResult(a, error=e) for a, e in started.items() if isinstance(e, ChipError)}

    def read_all(self, chips: list[MLX90393], zyxt: int) -> dict[int, ChipResult]:
        decoded = self.batch(chips, lambda c: c.rm_messages(zyxt), lambda c, r: c.decode_measurement(r, zyxt))
        return {a: ChipResult(a, error=v) if isinstance(v, ChipError) else ChipResult(a, v) for a, v in decoded.items()}

    def refused(self, exc: OSError) -> None:
        """A transfer failed: a refused shape (not a NACK) means the adapter takes less
        than was learnt; ask again at the next cycle, the narrowest shape until then."""
        if exc.errno in SHAPE_REFUSED:
            log.warning("the I2C adapter refused a transfer (%s): learning again what it takes", exc)
            self.shapes, self.reprobe = Shapes(), True

    @staticmethod
    def _decode_sm(chip: MLX90393, reply: bytes) -> None:
        status = mlx.Status(reply[0])
        if status.error and status.sm_mode:
            return  # it got the SM before its batch failed, and is converting
        chip.decode_sm(reply)

    def batch(self, chips: list[MLX90393], messages: Callable, decode: Callable) -> dict[int, Any]:
        """One transfer per as many chips as the adapter takes (`Shapes`); when one
        of several fails, each of its chips on its own.

        Returns per address what ``decode(chip, reply)`` gave, or the `ChipError`.
        """
        out: dict[int, Any] = {}
        alone: list[MLX90393] = []
        per = self.shapes.pairs_per_transfer
        for k in range(0, len(chips), per):
            group = chips[k:k + per]
            if len(group) == 1:
                alone.extend(group)  # one chip: its own transfer, its own error
                continue
            pairs = [messages(c) for c in group]
            try:
                self.bus.i2c_rdwr(*[m for pair in pairs for m in pair])
            except OSError as exc:
                self.refused(exc)
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
