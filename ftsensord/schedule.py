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
from .driver import MLX90393, T_AFTER_RT_S, Measurement
from .errors import ChipError, ChipNotRespondingError, ChipProtocolError, ChipRefusedError, ConfigError

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


@dataclass
class ChipResult:
    """What one cycle got from one chip: a measurement, or why not."""

    address: int
    measurement: Measurement | None = None
    error: ChipError | None = None

    @property
    def ok(self) -> bool:
        return self.measurement is not None


#: Backoff of a chip that does not come back: retried on the next cycle, then after
#: 20 ms doubling up to 0.5 s, so a returning chip is in use again within 0.5 s plus its
#: re-initialisation (at most three cycles), inside the 1 s the reliability figures ask.
BACKOFF_FIRST_S = 0.02
BACKOFF_MAX_S = 0.5
#: Identical X, Y, Z words this many cycles in a row by chance, on a chip at rest, may
#: happen at most this often per chip and cycle: 16 chips at 100 Hz make 5e10 chances a
#: year, so a false "stuck" once in 20 years.
STUCK_FALSE_ODDS = 1e-12
#: Beyond this many cycles (10 s at 100 Hz) a stuck chip would be found too late to
#: matter: the noise is far below an LSB and identical words are normal; detection is off.
STUCK_MAX_CYCLES = 1000


def stuck_cycles_for(settings: mlx.Settings) -> int:
    """Cycles of identical X, Y, Z words that mean a stuck chip at ``settings``; 0: off.

    Worst case, the field sits at the centre of a code: each reading keeps it with
    probability erf(LSB / (2 sqrt(2) sigma)) per axis (sigma: `mlx.noise_ut`, an
    estimate). At the paper's settings (2-3 uT of noise, 6-10 uT LSB) that is 0.67 for
    all three axes, and 70 cycles; heavy filtering (OSR 3, DIG_FILT 7) turns it off.
    """
    keep = math.prod(math.erf(settings.sensitivity_ut(a) / (2 * math.sqrt(2) * settings.noise_ut(a))) for a in "xyz")
    if keep >= 1.0:
        return 0
    n = math.ceil(math.log(STUCK_FALSE_ODDS) / math.log(keep))
    return n if n <= STUCK_MAX_CYCLES else 0


#: A chip that has had no new data this many cycles in a row is re-initialised.
STALE_LIMIT = 10


@dataclass
class ChipHealth:
    """What the reader knows of one chip beyond its last result."""

    failing: bool = False
    retry_at: float = 0.0
    backoff_s: float = 0.0
    reinits: int = 0
    register_drifts: int = 0
    stuck_detections: int = 0
    same_words: int = 0
    last_words: tuple[int, ...] | None = None
    stale_run: int = 0
    needs_reset: bool = False  # failed in a way only a reset mends (stuck, registers changed)
    step: int = 0  # the next step of a re-initialisation under way (0: none)
    step_at: float = 0.0  # when its previous step was sent (s, bus clock)


@dataclass
class Reader:
    """Reads every chip once a cycle with one of the `SCHEDULERS`, and keeps them healthy.

    Healthy chips share batched transfers. A NACK aborts a whole transfer, so
    when a batch fails its chips are tried one by one. A chip that fails (no
    answer, a bad reply, stuck data, no new data for too long, registers that
    changed) leaves the batches and is re-initialised (reset, configure, burst)
    when its retry is due, with backoff; it rejoins once that succeeds. Every
    ``readback_every`` cycles one chip's configuration is read back and compared
    (round robin: with 16 chips, each every 16 cycles at the default of 1).
    """

    bus: Bus
    chips: list[MLX90393]
    scheduler: str
    settings: mlx.Settings
    bus_hz: float = 400e3
    overhead_s: float = 0.0
    stuck_cycles: int | None = None  # None: `stuck_cycles_for` the settings
    readback_every: int = 1
    health: dict[int, ChipHealth] = field(default_factory=dict)
    cycle: int = 0

    def __post_init__(self) -> None:
        if self.scheduler not in SCHEDULERS:
            raise ConfigError(f"scheduler: expected one of {', '.join(SCHEDULERS)}, got {self.scheduler!r}")
        self.health = {c.address: ChipHealth() for c in self.chips}
        if self.stuck_cycles is None:
            self.stuck_cycles = stuck_cycles_for(self.settings)
        self._attempted = False  # one recovery a cycle

    @property
    def failing(self) -> set[int]:
        return {a for a, h in self.health.items() if h.failing}

    def conversion_s(self, zyxt: int) -> float:
        return self.settings.single_measurement_us(zyxt) * 1e-6 * OSC_MARGIN

    def _init(self, chip: MLX90393) -> None:
        chip.reset()
        chip.configure(self.settings)
        if self.scheduler == "burst":
            chip.start_burst(mlx.ZYXT_XYZ)

    def start(self) -> dict[int, ChipError]:
        """Reset and configure every chip (and start burst mode); returns the failures."""
        errors = {}
        for chip in self.chips:
            try:
                self._init(chip)
            except ChipError as exc:
                errors[chip.address] = exc
                self._fail(chip.address, self.bus.monotonic())
        return errors

    def stop(self) -> None:
        """Put every chip back to idle (EX), ignoring the ones that do not answer."""
        for chip in self.chips:
            try:
                chip.exit_mode()
            except ChipError:
                pass

    def _fail(self, address: int, now: float, reset: bool = False) -> None:
        h = self.health[address]
        h.needs_reset |= reset
        if not h.failing:
            h.failing, h.backoff_s, h.retry_at = True, 0.0, now  # first retry: the next cycle
        else:
            h.backoff_s = min(max(2 * h.backoff_s, BACKOFF_FIRST_S), BACKOFF_MAX_S)
            h.retry_at = now + h.backoff_s
        h.same_words, h.last_words, h.stale_run = 0, None, 0

    def _recover(self, chip: MLX90393, now: float) -> ChipResult:
        """A failing chip: one step of bringing it back when its retry is due and
        this cycle has not spent its one attempt; no data this cycle.

        A chip whose registers are intact needs one step (read them back, 0.5 ms).
        Otherwise a reset goes one command a cycle, EX, RT, configure, the
        datasheet's waits (1 ms, 2 ms) falling between cycles: a reset in one
        go would cost 4.4 ms, more than a cycle's slack at 100 Hz, and 16 chips
        after a bus-wide fault would cost whole cycles.
        """
        h = self.health[chip.address]
        wait_s = (0.0, mlx.T_AFTER_EX_US * 1e-6, T_AFTER_RT_S)[h.step]
        if now < h.retry_at or now < h.step_at + wait_s or self._attempted:
            return ChipResult(chip.address, error=ChipNotRespondingError(
                chip.address, f"failing; next retry in {max(0.0, h.retry_at - now):.2f} s"))
        self._attempted = True
        try:
            if h.step == 0 and not h.needs_reset and self._still_configured(chip):
                how = "answers again with its configuration intact"
            elif h.step == 0:
                chip.exit_mode()
                h.step, h.step_at = 1, self.bus.monotonic()
                how = "reset under way (EX)"
            elif h.step == 1:
                chip.send_reset()
                h.step, h.step_at = 2, self.bus.monotonic()
                how = "reset under way (RT)"
            else:
                h.step = 0
                chip.configure(self.settings)
                if self.scheduler == "burst":
                    chip.start_burst(mlx.ZYXT_XYZ)
                h.reinits += 1
                how = "re-initialised"
        except ChipError as exc:
            h.step = 0
            self._fail(chip.address, now)
            return ChipResult(chip.address, error=exc)
        if h.step == 0:
            h.failing = h.needs_reset = False
            how += "; read again from the next cycle"
        return ChipResult(chip.address, error=ChipNotRespondingError(chip.address, how))

    def _still_configured(self, chip: MLX90393) -> bool:
        """A chip back from a glitch usually kept its registers: three reads (0.5 ms)
        spare it a reset (4.4 ms, most of it the datasheet's waits). False when it
        lost them (it lost power) or refuses (a stray mode)."""
        if chip.settings is None:
            return False
        try:
            if self.scheduler == "burst":
                chip.exit_mode()
            if not chip.configuration_matches():
                return False
            if self.scheduler == "burst":
                chip.start_burst(mlx.ZYXT_XYZ)
        except ChipRefusedError:
            return False
        return True

    def read(self, zyxt: int = mlx.ZYXT_XYZ) -> list[ChipResult]:
        """One cycle: a result for every chip, in the order of ``chips``.

        ``zyxt`` picks the items (add T now and then for the temperature); burst
        mode reads what it was started with, X, Y and Z.
        """
        if self.scheduler == "burst":
            zyxt = mlx.ZYXT_XYZ
        now = self.bus.monotonic()
        healthy = [c for c in self.chips if not self.health[c.address].failing]
        self._attempted = False
        # The longest-failing first: every chip gets its turn.
        due = sorted((c for c in self.chips if self.health[c.address].failing),
                     key=lambda c: self.health[c.address].retry_at)
        results = {c.address: self._recover(c, now) for c in due}
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
            results[chip.address] = self._judge(results[chip.address], now)
        self._read_back(healthy, now)
        self.cycle += 1
        return [results[c.address] for c in self.chips]

    def _judge(self, r: ChipResult, now: float) -> ChipResult:
        """Update a healthy chip's health from its result; a stuck chip's data become an error."""
        h = self.health[r.address]
        if r.measurement is not None:
            h.stale_run = 0
            words = tuple(r.measurement.raw.get(a, -1) for a in "xyz")
            h.same_words = h.same_words + 1 if words == h.last_words else 0
            h.last_words = words
            if self.stuck_cycles and h.same_words >= self.stuck_cycles:
                h.stuck_detections += 1
                self._fail(r.address, now, reset=True)
                return ChipResult(r.address, error=ChipProtocolError(
                    r.address, f"stuck: the same X, Y, Z words {self.stuck_cycles + 1} cycles in a row"))
            return r
        if isinstance(r.error, ChipRefusedError) and r.error.command == "RM":
            h.stale_run += 1  # no new data (DRDY low): stale, unless it lasts
            if h.stale_run <= STALE_LIMIT:
                return r
        self._fail(r.address, now)
        return r

    def _read_back(self, healthy: list[MLX90393], now: float) -> None:
        """Every ``readback_every`` cycles, compare one chip's registers with what was written."""
        if not self.readback_every or self.cycle % self.readback_every or not healthy:
            return
        chip = healthy[(self.cycle // self.readback_every) % len(healthy)]
        if self.health[chip.address].failing:
            return
        try:
            if self.scheduler == "burst":
                chip.exit_mode()  # RR is refused in burst mode
            matches = chip.configuration_matches()
            if self.scheduler == "burst" and matches:
                chip.start_burst(mlx.ZYXT_XYZ)
        except ChipError:
            matches = False
        if not matches:
            self.health[chip.address].register_drifts += 1
            self._fail(chip.address, now, reset=True)

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
