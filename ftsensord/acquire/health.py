"""Chip health: what a cycle's result says of a chip, and bringing a failing chip back.

`ChipCare` judges each healthy chip's result (stuck words, no new data for too
long), takes a failing chip out with backoff, re-initialises it one command a
cycle, and reads one chip's registers back now and then. The `Reader`
(``reader.py``) decides how the bus is driven; this module, what to trust.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

from ftsensord.chip import mlx90393 as mlx
from ftsensord.chip.driver import MLX90393, T_AFTER_RT_S, Measurement
from ftsensord.chip.i2c import Bus
from ftsensord.errors import ChipError, ChipNotRespondingError, ChipProtocolError, ChipRefusedError

log = logging.getLogger("ftsensord")


@dataclass(slots=True)
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
#: A chip that has had no new data this many cycles in a row is re-initialised.
STALE_LIMIT = 10


def stuck_cycles_for(settings: mlx.Settings) -> int:
    """Cycles of identical X, Y, Z words that mean a stuck chip at ``settings``; 0: off.

    Worst case, the field sits at the centre of a code: each reading keeps it with
    probability erf(LSB / (2 sqrt(2) sigma)) per axis (sigma: `mlx.noise_ut`, an
    estimate). At the paper's settings (2-3 uT of noise, 6-10 uT LSB) that is 0.67 for
    all three axes, and 70 cycles; heavy filtering (OSR 3, DIG_FILT 7) turns it off.
    """
    keep = math.prod(
        math.erf(settings.sensitivity_ut(a) / (2 * math.sqrt(2) * settings.noise_ut(a))) for a in "xyz"
    )
    if keep >= 1.0:
        return 0
    n = math.ceil(math.log(STUCK_FALSE_ODDS) / math.log(keep))
    return n if n <= STUCK_MAX_CYCLES else 0


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
    stuck_words: tuple[int, ...] | None = None  # the words it was stuck at: out until they change
    stale_run: int = 0
    needs_reset: bool = False  # failed in a way only a reset mends (stuck, registers changed)
    step: int = 0  # the next step of a re-initialisation under way (0: none)
    step_at: float = 0.0  # when its previous step was sent (s, bus clock)


def _still_configured(chip: MLX90393, burst: bool, burst_zyxt: int) -> bool:
    """A chip back from a glitch usually kept its registers: three reads (0.5 ms)
    spare it a reset (4.4 ms, most of it the datasheet's waits). False when it
    lost them (it lost power) or refuses (a stray mode). ``burst``: the chips run in
    burst mode (converting ``burst_zyxt``), which RR refuses: EX first, SB after."""
    if chip.settings is None:
        return False
    try:
        if burst:
            chip.exit_mode()
        if not chip.configuration_matches():
            return False
        if burst:
            chip.start_burst(burst_zyxt)
    except ChipRefusedError:
        return False
    return True


class ChipCare:
    """The health of every chip of one bus, and one recovery step a cycle.

    A chip that fails (no answer, a bad reply, stuck data, no new data for too
    long, registers that changed) is taken out and re-initialised (reset,
    configure, burst) when its retry is due, with backoff; it rejoins once that
    succeeds. ``burst``: the chips run in burst mode, which RR refuses, so a
    read-back goes EX, RR, SB.
    """

    def __init__(
        self,
        bus: Bus,
        chips: list[MLX90393],
        settings: mlx.Settings,
        *,
        burst: bool,
        stuck_cycles: int | None = None,
        burst_zyxt: int = mlx.ZYXT_XYZ,
    ):
        self.bus, self.burst = bus, burst
        self.burst_zyxt = burst_zyxt  # what a burst converts: X, Y, Z, and T when temperatures are read
        self.health = {c.address: ChipHealth() for c in chips}
        self.use(settings, stuck_cycles)
        self._attempted = False  # one recovery a cycle
        self.turns = 0  # bumped as a chip starts or stops failing: `healthy` keeps its list till then
        self._healthy: tuple[int, list[MLX90393], list[MLX90393]] = (-1, [], [])

    def use(self, settings: mlx.Settings, stuck_cycles: int | None = None) -> None:
        """The chips' settings from now on (what a re-initialisation writes) and the identical
        readings that mean a stuck chip (None: `stuck_cycles_for` those settings: a longer
        conversion is quieter, and its words repeat more often at rest)."""
        self.settings = settings
        self.stuck_cycles = stuck_cycles_for(settings) if stuck_cycles is None else stuck_cycles

    @property
    def failing(self) -> set[int]:
        return {a for a, h in self.health.items() if h.failing}

    def healthy(self, chips: list[MLX90393]) -> list[MLX90393]:
        """``chips`` that are not failing: the same list, made once, while none starts or stops."""
        turns, of, kept = self._healthy
        if turns != self.turns or of is not chips:
            kept = [c for c in chips if not self.health[c.address].failing]
            self._healthy = (self.turns, chips, kept)
        return kept

    def new_cycle(self) -> None:
        self._attempted = False

    def initialise(self, chip: MLX90393) -> None:
        """Reset and configure a chip (and start burst mode) in one go."""
        chip.reset()
        self._configure(chip, self.settings)

    def rewrite(self, chip: MLX90393, settings: mlx.Settings) -> None:
        """A running chip's registers written with ``settings`` (`Reader.convert`): in burst,
        EX first (a chip in burst refuses WR) and burst mode started again after."""
        if self.burst:
            chip.exit_mode()
        self._configure(chip, settings)

    def _configure(self, chip: MLX90393, settings: mlx.Settings) -> None:
        """An idle chip configured with ``settings``, and burst mode started when the chips run it."""
        chip.configure(settings)
        if self.burst:
            chip.start_burst(self.burst_zyxt)

    def fail(self, address: int, now: float, reset: bool = False, why: str = "") -> None:
        """Take a chip out (``reset``: only a reset mends it); logged once, as it starts failing."""
        h = self.health[address]
        h.needs_reset |= reset
        if not h.failing:
            log.warning(
                "chip 0x%02X failing%s: %s",
                address,
                ", to be reset" if reset else "",
                why or "no valid answer",
            )
            h.failing, h.backoff_s, h.retry_at = True, 0.0, now  # first retry: the next cycle
            self.turns += 1
        else:
            h.backoff_s = min(max(2 * h.backoff_s, BACKOFF_FIRST_S), BACKOFF_MAX_S)
            h.retry_at = now + h.backoff_s
        h.same_words, h.last_words, h.stale_run = 0, None, 0

    def recover(self, chip: MLX90393, now: float) -> ChipResult:
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
            return ChipResult(
                chip.address,
                error=ChipNotRespondingError(
                    chip.address, f"failing; next retry in {max(0.0, h.retry_at - now):.2f} s"
                ),
            )
        self._attempted = True
        try:
            if h.step == 0 and not h.needs_reset and _still_configured(chip, self.burst, self.burst_zyxt):
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
                self._configure(chip, self.settings)
                h.reinits += 1
                how = "re-initialised"
        except ChipError as exc:
            h.step = 0
            self.fail(chip.address, now, why=str(exc))
            return ChipResult(chip.address, error=exc)
        if h.step == 0:
            h.failing = h.needs_reset = False
            self.turns += 1
            log.info("chip 0x%02X back: %s", chip.address, how)
            how += "; read again from the next cycle"
        return ChipResult(chip.address, error=ChipNotRespondingError(chip.address, how))

    def judge_all(self, results: dict[int, ChipResult], chips: list[MLX90393], now: float) -> None:
        """`judge` the results of ``chips`` (by address) that are healthy, in place; the
        usual one (new words from a chip in good standing) without a call of its own."""
        health, judge = self.health, self.judge
        for chip in chips:
            a = chip.address
            r = results.get(a)
            if r is None:
                continue
            h = health[a]
            if h.failing:
                continue
            m = r.measurement
            if m is not None and h.stuck_words is None:
                words = m.xyz_words()
                if words != h.last_words:  # `judge`'s usual cycle, as it does it
                    h.stale_run, h.last_words, h.same_words = 0, words, 0
                    continue
            results[a] = judge(r, now)

    def judge_words(
        self, addresses: tuple[int, ...], words: Sequence[tuple[int, ...]], now: float
    ) -> dict[int, ChipError]:
        """`judge` a clean cycle, every chip a measurement, from their X, Y, Z ``words``
        (in ``addresses``' order); the chips found stuck, with their errors."""
        health, stuck = self.health, None
        for a, w in zip(addresses, words):
            h = health[a]
            if w != h.last_words and h.stuck_words is None:  # `_words`'s usual cycle, as it does it
                h.stale_run, h.last_words, h.same_words = 0, w, 0
                continue
            error = self._words(h, a, w, now)
            if error is not None:
                stuck = stuck or {}
                stuck[a] = error
        return stuck or {}

    def judge(self, r: ChipResult, now: float) -> ChipResult:
        """Update a healthy chip's health from its result; a stuck chip's data become an error."""
        h = self.health[r.address]
        m = r.measurement
        if m is not None:
            error = self._words(h, r.address, m.xyz_words(), now)
            return r if error is None else ChipResult(r.address, error=error)
        if isinstance(r.error, ChipRefusedError) and r.error.command == "RM":
            h.stale_run += 1  # no new data (DRDY low): stale, unless it lasts
            if h.stale_run <= STALE_LIMIT:
                return r
        self.fail(r.address, now, why=str(r.error))
        return r

    def _words(self, h: ChipHealth, address: int, words: tuple[int, ...], now: float) -> ChipError | None:
        """A healthy chip's new reading, by its X, Y, Z words: None, or why its data are not to be used."""
        h.stale_run = 0
        last, h.last_words = h.last_words, words
        if words != last:
            h.same_words = 0
            if h.stuck_words is None:
                return None  # the usual cycle: new words from a chip in good standing
        else:
            h.same_words += 1
        moved = last is not None and words != last
        if self.stuck_cycles and h.same_words >= self.stuck_cycles:
            h.stuck_detections += 1
            self.fail(address, now, reset=True, why=f"stuck ({self.stuck_cycles + 1} identical readings)")
            h.stuck_words = words
            return ChipProtocolError(
                address, f"stuck: the same X, Y, Z words {self.stuck_cycles + 1} cycles in a row"
            )
        if h.stuck_words is not None:
            # Back from its reset: out until two of its readings in a row differ (a
            # stuck chip may give one fresh reading after a reset, then freeze again).
            if not moved:
                return ChipProtocolError(address, "stuck before its reset: out until its words change")
            h.stuck_words = None  # it converts again
        return None

    def read_back(self, chip: MLX90393, now: float) -> None:
        """Compare ``chip``'s registers with what was written; a chip that differs is reset."""
        if self.health[chip.address].failing:
            return
        try:
            if self.burst:
                chip.exit_mode()  # RR is refused in burst mode
            matches = chip.configuration_matches()
            if self.burst and matches:
                chip.start_burst(self.burst_zyxt)
        except ChipNotRespondingError as exc:
            # A NACK says nothing of the registers: the chip is retried like any chip that
            # did not answer (registers checked on its return), not counted as drift, not reset.
            self.fail(chip.address, now, why=f"no answer to the register read-back ({exc})")
            return
        except ChipError:
            matches = False  # refused or garbled: its state is unknown, only a reset mends it
        if not matches:
            self.health[chip.address].register_drifts += 1
            self.fail(chip.address, now, reset=True, why="registers differ from what was written")
