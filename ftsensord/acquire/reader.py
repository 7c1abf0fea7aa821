"""Reading every chip once a cycle: the three schedulers and their batched transfers.

- ``naive``: for each chip in turn, SM, wait for its conversion, RM.
- ``overlapped``: SM to every chip in one transfer, wait for the conversions
  (which run in parallel), RM every chip in one transfer. The chip whose
  registers are read back this cycle is read back during the wait, then
  started, and read last.
- ``burst``: the chips convert on their own clock (SB once); a cycle is one
  RM transfer. The bus itself is then the limit.

Outside ``overlapped``, the cycle's register read-back waits for `Reader.upkeep`, called
once the cycle's samples are out, so no sample waits for it (about 1 ms of bus). In
``burst`` it restarts the chip's burst (EX, RR, SB), and that chip is read last in the
next cycle, the longest time for its new result; where the host's work on the samples
outlasts that time, the read-back comes right after the RM instead.

"One transfer" is as wide as the adapter allows (`bound.Shapes`), learnt by
`transfers.probe_shapes` at start and again after a refusal, so a refused ioctl is paid
once, not every cycle. How fast each can go is `bound.cycle_bound`; which
chips to trust and how a failing one comes back is `health.ChipCare`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

from ftsensord.acquire.bound import (
    OSC_MARGIN,
    SCHEDULERS,
    Shapes,
    last_offset_s,
    overlapped_rm_at,
    rm_bits_for,
)
from ftsensord.acquire.health import ChipCare, ChipHealth, ChipResult
from ftsensord.acquire.readings import Readings
from ftsensord.acquire.transfers import RMRead, Transfers, probe_shapes
from ftsensord.chip import mlx90393 as mlx
from ftsensord.chip.driver import MLX90393
from ftsensord.chip.i2c import BITS_PER_BYTE, Bus, BusTiming
from ftsensord.errors import ChipError, ChipProtocolError, ConfigError

__all__ = ["Readings", "Reader", "Transfers", "probe_shapes"]

log = logging.getLogger("ftsensord")

#: The host's work between a read and its `Reader.upkeep` is held at its peak, forgotten by
#: 1 % a cycle (half in 69 cycles, 0.7 s at 100 Hz): one quick cycle does not undo a slow one.
HOST_PEAK_DECAY = 0.99


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
    #: Temperatures are read now and then (`read`'s zyxt with T): a burst converts T too
    #: (TCONVT more a conversion) and the reads that want it take it.
    temperature: bool = False
    care: ChipCare = field(init=False)
    cycle: int = 0
    xfer: Transfers = field(init=False)
    turn: ReadBackTurn = field(init=False)
    _addresses: tuple[int, ...] = field(init=False)
    _index: dict[int, int] = field(init=False)

    def __post_init__(self) -> None:
        if self.scheduler not in SCHEDULERS:
            raise ConfigError(f"scheduler: expected one of {', '.join(SCHEDULERS)}, got {self.scheduler!r}")
        self.care = ChipCare(
            self.bus,
            self.chips,
            self.settings,
            burst=self.scheduler == "burst",
            stuck_cycles=self.stuck_cycles,
            burst_zyxt=mlx.ZYXT_XYZT if self.temperature else mlx.ZYXT_XYZ,
        )
        self.xfer = Transfers(self.bus, self.chips)
        self._addresses = tuple(c.address for c in self.chips)
        self._index = {a: i for i, a in enumerate(self._addresses)}
        self.turn = ReadBackTurn(burst=self.scheduler == "burst")
        timing = getattr(self.bus, "timing", None)
        if timing is not None:
            self.use_timing(timing)

    def use_timing(self, timing: BusTiming) -> None:
        """What the bus knows of itself (a simulated one, or a board measured by
        `acquire.board`) beats the configured figures in the wait it times."""
        if timing.clock_hz:
            self.bus_hz = timing.clock_hz
        if timing.ioctl_s is not None and timing.clock_hz:
            self.overhead_s = timing.ioctl_s

    @property
    def shapes(self) -> Shapes:
        """What the adapter takes in one ioctl, as learnt."""
        return self.xfer.shapes

    def _learn_shapes(self) -> None:
        self.xfer.learn(self.care.healthy(self.chips) or self.chips, self.cycle)

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
        if self.scheduler == "burst":
            # The last chip's SB was just sent: its first result comes one conversion later
            # (its oscillator the slowest), and a read before it would be refused.
            self.bus.sleep(self.conversion_s(self.care.burst_zyxt))
        return errors

    def care_for(self, stuck_cycles: int | None) -> None:
        """Stuck detection after ``stuck_cycles`` identical readings (None: as the settings ask)."""
        self.stuck_cycles = stuck_cycles
        self.care.use(self.settings, stuck_cycles)

    def convert(self, settings: mlx.Settings) -> None:
        """Between cycles: write ``settings`` (a new conversion, OSR and DIG_FILT) to every
        healthy chip (in burst: EX before, SB after), and time the reads by them from the next
        cycle. A failing chip takes them as it is re-initialised (reset, then configured).

        A chip that fails the write (no answer, a refusal, a register that does not hold it) is
        taken out to be reset, which brings it back at the running settings; the chips written
        before it are written back to them (one that fails that is taken out the same way), and
        the `ChipError` is raised: every chip then runs the running settings or is failing,
        none is left on the new ones unknown to the reader."""
        old, now = self.settings, self.bus.monotonic()
        written: list[MLX90393] = []
        try:
            for chip in self.care.healthy(self.chips):
                written.append(chip)  # before the write: a failure midway leaves it half-written
                self.care.rewrite(chip, settings)
        except ChipError as exc:
            failed = written.pop()
            self.care.fail(failed.address, now, reset=True, why=f"refused the new conversion ({exc})")
            for chip in written:
                try:
                    self.care.rewrite(chip, old)
                except ChipError as back:
                    self.care.fail(chip.address, now, reset=True, why=f"refused its conversion back ({back})")
            raise
        for chip in self.chips:
            if self.health[chip.address].failing:
                self.health[chip.address].needs_reset = True  # its registers intact are the old ones
        self.settings = settings
        self.care_for(self.stuck_cycles)
        if self.scheduler == "burst":  # as at `start`: the first result of the new conversion
            self.bus.sleep(self.conversion_s(self.care.burst_zyxt))

    def stop(self) -> None:
        """Put every chip back to idle (EX), ignoring the ones that do not answer."""
        for chip in self.chips:
            try:
                chip.exit_mode()
            except ChipError:
                pass

    def read(self, zyxt: int = mlx.ZYXT_XYZ) -> Readings:
        """One cycle: a result for every chip, by address (in the order of ``chips``).

        ``zyxt`` picks the items (add T now and then for the temperature); burst
        mode reads X, Y and Z, and T only if it converts it (``temperature``).
        """
        if self.scheduler == "burst" and not self.temperature:
            zyxt = mlx.ZYXT_XYZ
        late, self.turn.due = self.turn.due, None  # no `upkeep` since the last read
        if self.xfer.reprobe:
            self._learn_shapes()
        now = self.bus.monotonic()
        health = self.care.health
        healthy = self.care.healthy(self.chips)
        self.care.new_cycle()
        # The longest-failing first: every chip gets its turn.
        due = (
            []
            if len(healthy) == len(self.chips)
            else sorted(
                (c for c in self.chips if health[c.address].failing), key=lambda c: health[c.address].retry_at
            )
        )
        results = {c.address: self.care.recover(c, now) for c in due}
        checked = None
        if self.readback_every and self.cycle % self.readback_every == 0 and healthy:
            checked = healthy[(self.cycle // self.readback_every) % len(healthy)]
        rm = None
        if self.scheduler == "naive":
            results.update({c.address: self._single(c, zyxt) for c in healthy})
        elif self.scheduler == "overlapped":
            rm = self._overlapped(healthy, zyxt, checked, now, results)
            checked = None  # read back during the wait
        else:
            order = self.turn.order(healthy)
            t = self.bus.monotonic()
            rm = self.xfer.read_block(order, zyxt) if order else None
            self.turn.others_s = (self.bus.monotonic() - t) * (len(order) - 1) / max(1, len(order))
        # The usual cycle, every chip read cleanly, stays in arrays (`Readings`) and is judged by its words.
        readings = None
        if rm is not None and not results:
            readings = Readings.of_block(rm, self.chips, self._addresses, self._index)
        if readings is not None and readings.words is not None:  # (of_block's readings carry their words)
            for a, error in self.care.judge_words(readings.addresses, readings.words, now).items():
                readings.fail(a, ChipResult(a, error=error))
        else:
            if rm is not None:
                results.update(self.xfer.results(rm))
            self.care.judge_all(results, healthy, now)
            readings = Readings(
                self._addresses, self._index, results={a: results[a] for a in self._addresses}
            )
        if late is not None:  # read back after the reads, as it came before `upkeep` existed
            self.care.read_back(late, now)
        elif checked is not None and not self.turn.may_wait():
            self.care.read_back(checked, now)
            checked = None
        self.turn.due = checked
        self.cycle += 1
        self.turn.read_end = self.bus.monotonic()
        return readings

    def upkeep(self) -> None:
        """The last `read`'s register read-back of one chip, left until its samples are
        out (``naive``, ``burst``; ``overlapped`` reads back during its wait). Call it
        after each `read` once the samples are sent; a `read` finding it not called
        reads back after its own reads, one cycle late, as before it existed."""
        now = self.bus.monotonic()
        chip = self.turn.upkept(now)
        if chip is not None:
            self.care.read_back(chip, now)

    def _overlapped(
        self,
        healthy: list[MLX90393],
        zyxt: int,
        checked: MLX90393 | None,
        now: float,
        results: dict[int, ChipResult],
    ) -> RMRead | None:
        """SM every chip, wait, RM every chip; ``checked`` is read back while the others
        convert, then started and read last (`bound.cycle_bound` counts the same). The
        chips that failed before the RM go into ``results``."""
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
                results[checked.address] = ChipResult(
                    checked.address,
                    error=ChipProtocolError(
                        checked.address,
                        "its registers read back differ from what was written: re-initialising",
                    ),
                )
            else:
                t_sm = self.bus.monotonic()
                results.update(self.xfer.start_all([checked], zyxt))
                if checked.address not in results:
                    ready.append(checked)
                    last_offset = last_offset_s(
                        len(ready),
                        rm_bits_for(zyxt),
                        self.shapes.pairs_per_transfer,
                        self.bus_hz,
                        self.overhead_s,
                    )
                    sm_one = self.bus.monotonic() - t_sm
                    # Measured from the cycle's start, as the bound computes it.
                    rm_at = overlapped_rm_at(
                        first + conversion, t_sm - t0, conversion, first, last_offset, sm_one
                    )
                    self.bus.sleep(max(0.0, t0 + rm_at - self.bus.monotonic()))
        if last_offset is None:
            self.bus.sleep(max(0.0, t0 + first + conversion - self.bus.monotonic()))
        return self.xfer.read_block(ready, zyxt) if ready else None

    def _single(self, chip: MLX90393, zyxt: int) -> ChipResult:
        try:
            chip.start_single(zyxt)
            self.bus.sleep(self.conversion_s(zyxt))
            return ChipResult(chip.address, chip.read_measurement(zyxt))
        except ChipError as exc:
            return ChipResult(chip.address, error=exc)


@dataclass
class ReadBackTurn:
    """When the cycle's register read-back comes, outside ``overlapped``: after the samples
    are sent (`Reader.upkeep`), the chip it restarts in burst read last the next cycle,
    while the host's work from a read to its upkeep (``host_s``, peak-held, s) is shorter
    than the other chips' RMs (``others_s``, s), which is all that chip then gets for its
    new burst result; else right after the RM."""

    burst: bool
    due: MLX90393 | None = None  # this cycle's, left to `upkeep`
    last: MLX90393 | None = None  # burst: restarted by the last read-back, read last
    read_end: float | None = None  # when the last read returned (bus clock), s
    host_s: float = 0.0
    others_s: float = 0.0

    _orders: dict[MLX90393, list[MLX90393]] = field(default_factory=dict)  # `order`'s, of `_of`
    _of: list[MLX90393] | None = None

    def order(self, healthy: list[MLX90393]) -> list[MLX90393]:
        """``healthy`` in the order to read them: the chip the last read-back restarted last
        (the same list each time for the same chips: `ChipCare.healthy` keeps them)."""
        last = self.last
        if last is None:
            return healthy
        if healthy is not self._of:
            self._orders, self._of = {}, healthy
        got = self._orders.get(last)
        if got is None:
            got = self._orders[last] = (
                healthy if last not in healthy else [c for c in healthy if c is not last] + [last]
            )
        return got

    def may_wait(self) -> bool:
        return not self.burst or self.host_s <= self.others_s

    def upkept(self, now: float) -> MLX90393 | None:
        """The chip to read back now (None: none due), the host's work learnt."""
        if self.read_end is not None:
            self.host_s = max(now - self.read_end, self.host_s * HOST_PEAK_DECAY)
        chip, self.due = self.due, None
        self.last = chip if self.burst else None
        return chip
