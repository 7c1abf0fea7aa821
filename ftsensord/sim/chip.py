"""An emulated MLX90393: register file and command state machine.

It answers the same bytes the chip does. The simulated bus hands it each
message with the time that message is on the wire, so conversions take the
datasheet's time on whatever clock the bus runs (virtual or real). The field
it measures comes from a scene (``scene.field_t(address, t)``), so the chip
emulation and the physics stay apart.

Where the datasheet is silent, the emulator picks the stricter behaviour so
that a driver bug shows up here rather than on a real board; each such choice
says so in a comment.
"""

from __future__ import annotations

import enum
import functools
import math

import numpy as np

from ftsensord.chip import mlx90393 as mlx
from ftsensord.sim.conversion import NOISELESS, Conversions, FieldSource, NoiseModel
from ftsensord.sim.heat import ChipDrift

__all__ = ["NOISELESS", "EmulatedMLX90393", "FieldSource", "Mode", "NoiseModel"]


class Mode(enum.Enum):
    IDLE = 0
    SINGLE = mlx.STATUS_SM_MODE
    BURST = mlx.STATUS_BURST_MODE
    WOC = mlx.STATUS_WOC_MODE


_MODE_OF_OPCODE = {mlx.CMD_SM: Mode.SINGLE, mlx.CMD_SB: Mode.BURST, mlx.CMD_SW: Mode.WOC}


class RegisterCommands:
    """The status byte and the register commands of `EmulatedMLX90393` (RR, WR, HR,
    HS, a register drifting by itself): a part of the chip kept apart so that each
    class stays readable."""

    registers: list[int]
    nonvolatile: list[int]
    mode: Mode
    busy_until: float
    _d_rng: np.random.Generator
    _pending_drifts: list[tuple[float, int, int]]

    def _status(self, *, error: bool = False, d: int | None = None, rs: bool = False) -> bytes:
        """The status byte; ``d`` None for a reply without data.

        Logic captures of real chips show D1:D0 set in replies that carry no data:
        EX and WR 0x01 or 0x02, RT 0x05 or 0x06, SM (xyz) 0x21 or 0x22. The emulator
        draws 1 or 2 for every such reply (SB, SW, HR, HS and refusals too, where no
        capture exists: SB's 0x81/0x82 follows SM's pattern with its own mode bit),
        so a driver that compares whole status bytes, or waits for a zero D, fails
        here as it would on a board.
        """
        if d is None:
            d = int(self._d_rng.integers(1, 3))
        byte = self.mode.value | (mlx.STATUS_ERROR if error else 0) | (mlx.STATUS_RS if rs else 0) | d
        return bytes([byte])

    def drift_register(self, reg: int, value: int, at: float | None = None) -> None:
        """Fault: register ``reg`` takes ``value`` by itself (now, or at time ``at``)."""
        if at is None:
            self.registers[reg] = value
        else:
            self._pending_drifts.append((at, reg, value))

    def _register_address(self, byte: int) -> int | None:
        # The address travels as reg << 2; set low bits make it malformed
        # (emulator's choice: refuse rather than guess).
        return None if byte & 0x03 else byte >> 2

    def _rr(self, opcode: int, zyxt: int, data: bytes, now: float) -> bytes:
        reg = self._register_address(data[1]) if len(data) == 2 else None
        if reg is None or self.mode in (Mode.BURST, Mode.WOC):
            return self._status(error=True)
        return self._status(d=0) + self.registers[reg].to_bytes(2, "big")

    def _wr(self, opcode: int, zyxt: int, data: bytes, now: float) -> bytes:
        reg = self._register_address(data[3]) if len(data) == 4 else None
        # SINGLE is a conversion under way (it ends in IDLE): the datasheet is silent on a WR
        # then, so the strict choice, refused, as in burst.
        if reg is None or reg > mlx.REG_CUSTOMER_MAX or self.mode is not Mode.IDLE:
            return self._status(error=True)
        self.registers[reg] = (data[1] << 8) | data[2]
        return self._status()

    def _hr(self, opcode: int, zyxt: int, data: bytes, now: float) -> bytes:
        if self.mode is not Mode.IDLE:
            return self._status(error=True)
        self.registers[: len(self.nonvolatile)] = self.nonvolatile
        return self._status()

    def _nop(self, opcode: int, zyxt: int, data: bytes, now: float) -> bytes:
        """NOP (0x00): the status, nothing else changes, in any mode (Melexis's own driver
        defines MLX90393_CMD_NOP 0x00 and sends it like EX: docs/design/simulator.md). Only the
        one byte 0x00: 0x01-0x0F, or more bytes, are no listed command (refused)."""
        return self._status(error=data != bytes([mlx.CMD_NOP]))

    def _hs(self, opcode: int, zyxt: int, data: bytes, now: float) -> bytes:
        if self.mode is not Mode.IDLE:
            return self._status(error=True)
        self.nonvolatile = list(self.registers[: len(self.nonvolatile)])
        self.busy_until = now + mlx.T_HS_US * 1e-6
        return self._status()


class EmulatedMLX90393(RegisterCommands, Conversions):
    """One chip at one address. Times (``now``) are seconds on the bus's clock.

    ``drift``: how it drifts with its die temperature (None: not at all), by its own TCMP_EN.

    Fault hooks for tests: ``stuck`` (the same data forever, DRDY always high),
    ``memory_error`` (a double-bit ECC error: every command but RT refused),
    `drift_register` (a register that changes by itself), ``oscillator`` (this chip's
    conversion times against nominal: the datasheet's +-20 % is 0.8 to 1.2; the slowest by default).
    """

    def __init__(
        self,
        address: int,
        scene: FieldSource,
        *,
        rng: np.random.Generator | None = None,
        noise: NoiseModel = NoiseModel(),
        tref: int = mlx.TREF_TYPICAL,
        drift: ChipDrift | None = None,
    ):
        mlx.part_variant(address)
        self.address = address
        self.scene = scene
        self.drift = drift
        self.rng = rng if rng is not None else np.random.default_rng(address)
        # D1:D0 of replies without data vary on their own stream, so the noise a seed
        # gives stays what it was (spawning does not advance ``rng``).
        seed_seq = getattr(self.rng.bit_generator, "seed_seq", None)
        self._d_rng = np.random.default_rng(seed_seq.spawn(1)[0] if seed_seq is not None else address)
        self.noise = noise
        self.tref = tref
        # Non-volatile memory: what power-on and RT load into the registers.
        self.nonvolatile = [0] * (mlx.REG_CUSTOMER_MAX + 1)
        for reg, value in mlx.POWER_ON_DEFAULTS.items():
            self.nonvolatile[reg] = value
        self.stuck = False
        self.memory_error = False
        # Times nominal: the slowest a real chip may be (a driver that waits the nominal time
        # reads too early on such a chip, so it must here too); tests set 0.8 for the fastest.
        self.oscillator = mlx.OSCILLATOR_SLOWEST
        self.field_override: np.ndarray | None = None  # fault: a field from elsewhere (T)
        self._pending_drifts: list[tuple[float, int, int]] = []
        self.power_on()

    # --- state ------------------------------------------------------------------
    def power_on(self) -> None:
        """Power-on: registers from non-volatile memory, idle, no data."""
        self.registers = [0] * (mlx.REG_MAX + 1)
        self.registers[: len(self.nonvolatile)] = self.nonvolatile
        self.registers[mlx.REG_TREF] = self.tref
        self.mode = Mode.IDLE
        self.busy_until = -math.inf
        self.reply = b""
        self._reply_pending = False  # a command whose reply has not been read yet
        self._sm_unread = False  # an accepted SM whose status byte has not been read yet
        self._conv_items: tuple[str, ...] = ()
        self._conv_setup: tuple[mlx.Settings, tuple[int, ...]] | None = None  # settings, offsets at its start
        self._conv_first = math.inf  # time the first result is ready
        self._conv_interval = math.inf  # burst interval (inf: one conversion only)
        self._last_index = -1  # index of the newest result already read
        self._stuck_words: dict[str, int] | None = None

    def settings(self) -> mlx.Settings:
        return _settings_of(
            self.registers[mlx.REG_CONF1], self.registers[mlx.REG_CONF2], self.registers[mlx.REG_CONF3]
        )

    def acks(self, now: float, reading: bool = False) -> bool:
        """Whether the chip acknowledges its address.

        A read is acknowledged only after a command whose reply it reads, once:
        captures show a real chip NACKs a bare read (``i2cdetect -r`` does not
        find it). After RT and HS it still sends the reply to that command,
        then NACKs new commands until its wait is over. The datasheet only says
        to wait; a chip whose digital core is restarting cannot answer, so the
        emulator NACKs rather than guessing a reply.
        """
        if reading:
            return self._reply_pending
        return now >= self.busy_until

    def _advance(self, now: float) -> None:
        for item in [d for d in self._pending_drifts if d[0] <= now]:
            self.registers[item[1]] = item[2]
            self._pending_drifts.remove(item)
        if self.mode is Mode.SINGLE and now >= self._conv_first:
            self.mode = Mode.IDLE  # the chip returns to idle with data ready

    def _newest_index(self, now: float) -> int:
        """Index of the newest finished conversion (-1: none yet)."""
        if now < self._conv_first:
            return -1
        if math.isinf(self._conv_interval):
            return 0
        return int((now - self._conv_first) // self._conv_interval)

    # --- bus side ---------------------------------------------------------------
    def write(self, data: bytes, now: float) -> None:
        """A write message: execute the command it carries and prepare the reply."""
        if not data:
            return  # a zero-length write is an address probe: ACK only
        self._advance(now)
        if self._sm_unread:
            self._void_single()
        self._reply_pending = True  # (set again below: RT's power-on clears it)
        opcode, zyxt = data[0] & 0xF0, data[0] & 0x0F
        if self.memory_error and opcode != mlx.CMD_RT:
            self.reply = self._status(error=True)
            return
        handler = {
            mlx.CMD_SB: self._mode_start,
            mlx.CMD_SW: self._mode_start,
            mlx.CMD_SM: self._mode_start,
            mlx.CMD_RM: self._rm,
            mlx.CMD_RR: self._rr,
            mlx.CMD_WR: self._wr,
            mlx.CMD_EX: self._ex,
            mlx.CMD_HR: self._hr,
            mlx.CMD_HS: self._hs,
            mlx.CMD_RT: self._rt,
            mlx.CMD_NOP: self._nop,
        }.get(opcode)
        if handler is None:
            self.reply = self._status(error=True)  # unknown opcode: refused
            return
        self.reply = handler(opcode, zyxt, data, now)
        self._reply_pending = True

    def read(self, length: int, now: float) -> bytes:
        """A read message: the prepared reply; 0xFF (released SDA) past its end."""
        self._advance(now)
        self._reply_pending = False
        self._sm_unread = False
        return (self.reply + b"\xff" * length)[:length]

    # --- commands -----------------------------------------------------------------
    def _selected(self, zyxt: int) -> tuple[str, ...]:
        return mlx.zyxt_items(zyxt or mlx.BURST_SEL.get(self.registers[mlx.REG_CONF2]))

    def _mode_start(self, opcode: int, zyxt: int, data: bytes, now: float) -> bytes:
        items = self._selected(zyxt)
        s = self.settings()
        # Refused: another mode active, nothing selected, or settings the
        # datasheet forbids (the emulator's choice: a real chip's output there
        # is undefined, and refusing shows the missing configure at once).
        if self.mode is not Mode.IDLE or not items or len(data) != 1:
            return self._status(error=True)
        if not _permitted(s):
            return self._status(error=True)
        self.mode = _MODE_OF_OPCODE[opcode]
        zyxt_eff = mlx.items_zyxt(items)
        self._conv_items = items
        # A single conversion is made with the settings it started with (the datasheet is silent on a
        # WR during one; a result already in the data registers cannot change): a later WR acts on the
        # next. A burst's results are each a conversion of their own, with the registers then (WR is
        # refused in burst: only a register drifting by itself changes them).
        self._conv_setup = (
            (s, tuple(self.registers[r] for r in mlx.REG_OFFSETS)) if self.mode is Mode.SINGLE else None
        )
        self._last_index = -1
        if self.mode is Mode.WOC:
            # Wake-on-change is accepted as a mode (status bit, exclusivity) but
            # never produces data here: ftsensord does not use it.
            self._conv_first, self._conv_interval = math.inf, math.inf
        else:
            self._conv_first = now + s.single_measurement_us(zyxt_eff) * 1e-6 * self.oscillator
            self._conv_interval = (
                s.burst_interval_us(zyxt_eff) * 1e-6 * self.oscillator
                if self.mode is Mode.BURST
                else math.inf
            )
        self._sm_unread = self.mode is Mode.SINGLE
        return self._status()

    def _void_single(self) -> None:
        """An SM whose status byte was never read (the next command came first): its
        measurement is as if never started, back to idle with no data, so the RM after
        it is refused (ERROR, SM_MODE clear). The datasheet: the first SM after power-up
        or reset "should have the status byte read back in order to get valid
        measurement data back"; the emulator takes the safest reading, for every SM (a
        chip may have reset unseen, so a driver cannot know which SM is the first), and
        refuses rather than return data a real chip may get wrong without a flag."""
        self._sm_unread = False
        if self.mode is Mode.SINGLE:
            self.mode = Mode.IDLE
        self._conv_first, self._conv_interval = math.inf, math.inf
        self._last_index = -1

    def _rm(self, opcode: int, zyxt: int, data: bytes, now: float) -> bytes:
        items = self._selected(zyxt)
        if self.stuck and self._stuck_words is not None and set(items) <= set(self._stuck_words):
            return self._reply_words(items, self._stuck_words)
        index = self._newest_index(now)
        # Refused: no new data since the last RM (DRDY low), or items asked for
        # that the conversion did not make (emulator's choice: refuse).
        if not items or index <= self._last_index or not set(items) <= set(self._conv_items):
            return self._status(error=True)
        self._last_index = index
        t_done = self._conv_first + (0.0 if math.isinf(self._conv_interval) else index * self._conv_interval)
        words = self._convert(t_done)
        if self.stuck:
            self._stuck_words = words
        return self._reply_words(items, words)

    def _ex(self, opcode: int, zyxt: int, data: bytes, now: float) -> bytes:
        self.mode = Mode.IDLE
        self._conv_first, self._conv_interval = math.inf, math.inf
        return self._status()

    def _rt(self, opcode: int, zyxt: int, data: bytes, now: float) -> bytes:
        # Quirk of real chips: RT may not clear burst mode; drivers send EX first.
        burst = self.mode is Mode.BURST
        first, interval = self._conv_first, self._conv_interval
        self.power_on()
        self.memory_error = False
        if burst:
            self.mode, self._conv_first, self._conv_interval = Mode.BURST, first, interval
        self.busy_until = now + mlx.T_AFTER_RT_US * 1e-6
        return self._status(rs=True)


@functools.lru_cache(maxsize=256)
def _settings_of(conf1: int, conf2: int, conf3: int) -> mlx.Settings:
    """The settings CONF1..CONF3 hold: parsed once per register words (the emulator asks
    at every conversion, and its CPU is spent inside the simulated transfers)."""
    return mlx.Settings.from_registers({mlx.REG_CONF1: conf1, mlx.REG_CONF2: conf2, mlx.REG_CONF3: conf3})


@functools.lru_cache(maxsize=256)
def _permitted(settings: mlx.Settings) -> bool:
    """Whether the datasheet permits ``settings`` (`mlx.Settings.validate`)."""
    try:
        settings.validate()
    except ValueError:
        return False
    return True
