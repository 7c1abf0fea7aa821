"""Driver for one MLX90393 at one I2C address.

The driver takes its bus: any object with smbus2's ``i2c_rdwr(*msgs)``
(``smbus2.SMBus``, or the simulated bus of `ftsensord.sim`). Each command is
one combined transaction: write the command bytes, repeated start, read the
reply whose first byte is the status byte. Acceptance is read from the status
byte, never from the ACK (the chip ACKs every byte, even of a bad command).

Every command is split into a message builder (``*_messages``) and a decoder
(``decode_*``), so a scheduler can put commands for many chips into one
``I2C_RDWR`` ioctl and still decode each reply with the same code.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from smbus2 import i2c_msg

from ftsensord.chip import mlx90393 as mlx
from ftsensord.errors import ChipNotRespondingError, ChipProtocolError, ChipRefusedError, RegisterVerifyError

#: Wait after RT before the next command: the datasheet asks for at least 1.5 ms.
T_AFTER_RT_S = 2e-3


class I2CBus(Protocol):
    """What the driver needs of a bus: smbus2's combined transfer."""

    def i2c_rdwr(self, *i2c_msgs: i2c_msg) -> None: ...


@dataclass(eq=False, slots=True)
class Measurement:
    """One RM result, in SI units and the chip's own frame {S_i}.

    ``field_t`` is (Bx, By, Bz) in tesla, NaN for an axis that was not read;
    ``saturated`` flags per axis a word at or past the valid span, or a field at
    the Hall element's limit: such an axis is never a valid reading.
    ``words``: the reply's 16-bit words, one per item of ``items`` in RM's order
    (``raw`` has them by item). ``saturated_any``: ``saturated.any()`` when the
    decoder already knows it.
    """

    status: mlx.Status
    field_t: np.ndarray
    saturated: np.ndarray
    temperature_c: float | None
    words: tuple[int, ...]
    items: tuple[str, ...] = mlx.zyxt_items(mlx.ZYXT_XYZ)
    saturated_any: bool | None = None

    @property
    def raw(self) -> dict[str, int]:
        """The words by item ("x", "y", "z", "t"); built when asked, not every cycle."""
        return dict(zip(self.items, self.words))

    def xyz_words(self) -> tuple[int, int, int]:
        """The X, Y, Z words, -1 for an axis not read (the stuck test compares them)."""
        if self.items is _XYZ:
            return self.words  # type: ignore[return-value]  # the usual RM: these three, in order
        raw = self.raw
        return raw.get("x", -1), raw.get("y", -1), raw.get("z", -1)

    @property
    def any_saturated(self) -> bool:
        return bool(self.saturated.any()) if self.saturated_any is None else self.saturated_any


_XYZ = mlx.zyxt_items(mlx.ZYXT_XYZ)


class MLX90393:
    """One chip: reset, registers, configuration, single and burst measurements.

    ``sleep`` waits the datasheet's times (reset); pass the simulated bus's
    ``sleep`` when its clock is virtual.
    """

    settings_changes = 0  # counts changes of any chip's settings: a `BlockDecoder` built before may be stale

    def __init__(self, bus: I2CBus, address: int, *, sleep: Callable[[float], None] = time.sleep):
        mlx.part_variant(address)  # refuses an address no MLX90393 can have
        self.bus, self.address, self.sleep = bus, address, sleep
        self.settings = None
        self.tref = mlx.TREF_TYPICAL
        self._msgs: dict[
            tuple[bytes, int], tuple[i2c_msg, i2c_msg]
        ] = {}  # per command (an i2c_msg: 2 buffers)
        self._expected: tuple[mlx.Settings | None, tuple[int, ...], dict[int, int]] | None = (
            None  # `_expected_for`'s
        )

    def __repr__(self) -> str:
        return f"MLX90393(address=0x{self.address:02X})"

    # --- transactions --------------------------------------------------------
    def messages(self, command: bytes, reply_len: int) -> tuple[i2c_msg, i2c_msg]:
        """The write and read messages of one command, built once and reused (the read's buffer: the last reply)."""
        key = (command, reply_len)
        pair = self._msgs.get(key)
        if pair is None:
            pair = self._msgs[key] = (
                i2c_msg.write(self.address, command),
                i2c_msg.read(self.address, reply_len),
            )
        return pair

    def transfer(self, command: bytes, reply_len: int) -> bytes:
        """Send ``command`` and read ``reply_len`` bytes (status byte first)."""
        write, read = self.messages(command, reply_len)
        try:
            self.bus.i2c_rdwr(write, read)
        except OSError as exc:
            raise bus_error(self.address, command, exc) from exc
        return read.buf[: read.len]  # bytes(read) is two Python calls more (smbus2's __bytes__, string_at)

    def check_status(self, byte: int, command: str) -> mlx.Status:
        """Decode a status byte; raise `ChipRefusedError` when ERROR is set."""
        status = mlx.status_of(byte)
        if status.error:
            raise ChipRefusedError(
                self.address, f"{command} refused, status {status}", status, command.split()[0]
            )
        return status

    def _check_mode(self, byte: int, mode_bit: int, name: str) -> mlx.Status:
        """A mode command's reply: no ERROR, and the mode bit it asked for set."""
        status = self.check_status(byte, name)
        if not status.byte & mode_bit:
            raise ChipProtocolError(self.address, f"{name} accepted without its mode bit, status {status}")
        return status

    # --- modes -----------------------------------------------------------------
    def exit_mode(self) -> mlx.Status:
        """EX: leave burst, wake-on-change or single-measurement mode."""
        return self.check_status(self.transfer(bytes([mlx.CMD_EX]), 1)[0], "EX")

    def reset(self) -> mlx.Status:
        """EX, wait 1 ms, RT, wait 2 ms: the datasheet's reset, safe from any mode.

        RT may not clear burst mode on its own, hence the EX first; the wait
        after RT is 2 ms where the datasheet asks for at least 1.5 ms.
        """
        self.exit_mode()
        self.sleep(mlx.T_AFTER_EX_US * 1e-6)
        status = self.send_reset()
        self.sleep(T_AFTER_RT_S)
        return status

    def send_reset(self) -> mlx.Status:
        """RT alone: the caller waits `T_AFTER_RT_S` before the next command (and
        sends EX, then waits 1 ms, before it when the chip may be in a mode)."""
        status = self.check_status(self.transfer(bytes([mlx.CMD_RT]), 1)[0], "RT")
        if not status.rs:
            raise ChipProtocolError(self.address, f"RT reply lacks RS, status {status}")
        self.settings = None
        return status

    def sm_messages(self, zyxt: int = mlx.ZYXT_XYZ) -> tuple[i2c_msg, i2c_msg]:
        return self.messages(bytes([mlx.CMD_SM | zyxt]), 1)

    def decode_sm(self, reply: bytes) -> mlx.Status:
        return self._check_mode(reply[0], mlx.STATUS_SM_MODE, "SM")

    def start_single(self, zyxt: int = mlx.ZYXT_XYZ) -> mlx.Status:
        """SM: start one conversion of the selected items (data ready after
        `mlx.Settings.single_measurement_us`)."""
        return self.decode_sm(self.transfer(bytes([mlx.CMD_SM | zyxt]), 1))

    def start_burst(self, zyxt: int = mlx.ZYXT_XYZ) -> mlx.Status:
        """SB: convert continuously on the chip's own clock (zyxt 0 uses BURST_SEL)."""
        return self._check_mode(self.transfer(bytes([mlx.CMD_SB | zyxt]), 1)[0], mlx.STATUS_BURST_MODE, "SB")

    # --- measurement -------------------------------------------------------------
    def rm_messages(self, zyxt: int = mlx.ZYXT_XYZ) -> tuple[i2c_msg, i2c_msg]:
        return self.messages(bytes([mlx.CMD_RM | zyxt]), _rm_reply_len(zyxt))

    def decode_measurement(self, reply: bytes, zyxt: int = mlx.ZYXT_XYZ) -> Measurement:
        """Decode an RM reply into tesla and degC, flagging saturated axes."""
        if self.settings is None:
            raise ChipProtocolError(self.address, "RM decoded before configure(): the scale is unknown")
        items = mlx.zyxt_items(zyxt)
        status = self.check_status(reply[0], "RM")
        if status.data_bytes != 2 * len(items) or len(reply) != 1 + 2 * len(items):
            raise ChipProtocolError(
                self.address,
                f"RM of {'/'.join(items).upper()} expects {2 * len(items)} data bytes, "
                f"status D1:D0 says {status.data_bytes} (status {status}, {len(reply) - 1} read)",
            )
        words = {item: (reply[1 + 2 * i] << 8) | reply[2 + 2 * i] for i, item in enumerate(items)}
        field = np.full(3, np.nan)
        saturated = np.zeros(3, dtype=bool)
        for i, axis in enumerate("xyz"):
            if axis in words:
                fmt, tesla_per_count = self._decoding[i]
                counts = mlx.raw_to_counts(words[axis], fmt)
                field[i] = value = counts * tesla_per_count
                saturated[i] = mlx.is_saturated(counts, fmt) or abs(value) >= mlx.HALL_SATURATION_FLAG_T
        temp = mlx.raw_to_celsius(words["t"], self.tref) if "t" in words else None
        return Measurement(status, field, saturated, temp, tuple(words.values()), items)

    def read_measurement(self, zyxt: int = mlx.ZYXT_XYZ) -> Measurement:
        """RM: read the selected items of the last conversion."""
        return self.decode_measurement(self.transfer(bytes([mlx.CMD_RM | zyxt]), _rm_reply_len(zyxt)), zyxt)

    def measure(self, zyxt: int = mlx.ZYXT_XYZ) -> Measurement:
        """SM, wait the nominal conversion time (+20 % for the oscillator), RM."""
        if self.settings is None:
            raise ChipProtocolError(self.address, "measure() before configure()")
        self.start_single(zyxt)
        self.sleep(self.settings.single_measurement_us(zyxt) * 1.2e-6)
        return self.read_measurement(zyxt)

    # --- registers -----------------------------------------------------------------
    def read_register(self, reg: int) -> int:
        """RR: one 16-bit register."""
        if not 0 <= reg <= mlx.REG_MAX:
            raise ValueError(f"register address 0x{reg:02X} is out of range 0x00-0x{mlx.REG_MAX:02X}")
        reply = self.transfer(bytes([mlx.CMD_RR, reg << 2]), 3)
        # The status by its bits: `Status`' properties cost a call each, every read-back.
        if reply[0] & mlx.STATUS_ERROR:  # raises, naming the register (a name built only then)
            self.check_status(reply[0], f"RR 0x{reg:02X}")
        if reply[0] & mlx.STATUS_D_MASK:  # D1:D0 = 0 for 2 data bytes (2 D + 2)
            raise ChipProtocolError(
                self.address, f"RR expects 2 data bytes, status {mlx.status_of(reply[0])}"
            )
        return (reply[1] << 8) | reply[2]

    def write_register(self, reg: int, value: int, *, verify: bool = True) -> None:
        """WR, then (by default) RR and compare: a register must hold what was written."""
        if not 0 <= reg <= mlx.REG_CUSTOMER_MAX:
            raise ValueError(f"register 0x{reg:02X} is not writable (customer area 0x00-0x1F)")
        if not 0 <= value <= 0xFFFF:
            raise ValueError(f"a register holds 16 bits, got {value!r}")
        reply = self.transfer(bytes([mlx.CMD_WR, value >> 8, value & 0xFF, reg << 2]), 1)
        self.check_status(reply[0], f"WR 0x{reg:02X}")
        if verify:
            back = self.read_register(reg)
            if back != value:
                raise RegisterVerifyError(
                    self.address, f"register 0x{reg:02X} reads 0x{back:04X} after writing 0x{value:04X}"
                )

    def read_configuration(self) -> dict[int, int]:
        """CONF1..CONF3 as the chip holds them now."""
        return {reg: self.read_register(reg) for reg in (mlx.REG_CONF1, mlx.REG_CONF2, mlx.REG_CONF3)}

    def configure(self, settings: mlx.Settings) -> None:
        """Validate ``settings`` and write them (`write_tcmp_offsets` first), keeping reserved bits as read.

        Raises `ForbiddenSettingError` before touching the chip when the datasheet
        does not permit the combination.
        """
        settings.validate()
        current = self.read_configuration()
        write_tcmp_offsets(self, settings)
        for reg, value in settings.to_registers(current).items():
            self.write_register(reg, value)
        self.tref = self.read_register(mlx.REG_TREF)
        self.settings = settings

    @property
    def settings(self) -> mlx.Settings | None:
        """What `configure` wrote (None before, or after a reset)."""
        return self._settings

    @settings.setter
    def settings(self, settings: mlx.Settings | None) -> None:
        self._settings = settings
        MLX90393.settings_changes += 1  # a `BlockDecoder` built before is stale
        # Per axis: the word's coding and tesla per count, fixed until the next configure.
        self._decoding = (
            []
            if settings is None
            else [(settings.raw_format(a), settings.sensitivity_ut(a) * 1e-6) for a in "xyz"]
        )

    def configuration_matches(self) -> bool:
        """Read back CONF1..CONF3 and compare with what `configure` wrote.

        Registers have been seen to change after months of running; a caller
        re-initialises the chip when this returns False. With TCMP_EN, OFFSET_X/Y/Z too.
        """
        if self.settings is None:
            raise ChipProtocolError(self.address, "not configured")
        current = self.read_configuration()  # CONF1, CONF2, CONF3, in this order
        return current == self._expected_for(tuple(current.values())) and tcmp_offsets_hold(self)

    def _expected_for(self, read: tuple[int, ...]) -> dict[int, int]:
        """`_expected_registers` for this chip's settings and CONF1..CONF3 as ``read``, kept
        while both stay (an lru_cache would hash the settings every read-back: 1 us)."""
        kept = self._expected
        if kept is None or kept[0] is not self.settings or kept[1] != read:
            assert self.settings is not None  # (a read-back runs only on a configured chip)
            kept = self._expected = (self.settings, read, _expected_registers(self.settings, *read))
        return kept[2]


def write_tcmp_offsets(chip: MLX90393, settings: mlx.Settings) -> None:
    """With TCMP_EN in ``settings``: OFFSET_X/Y/Z at `mlx.OFFSET_TCMP_ZERO`, before TCMP_EN
    turns on. The compensated output is referenced to them, and at their power-on 0 it is
    garbage. With TCMP_EN off the chip does not use them: left as they are."""
    if settings.tcmp_en:
        for reg in mlx.REG_OFFSETS:
            chip.write_register(reg, mlx.OFFSET_TCMP_ZERO)


def tcmp_offsets_hold(chip: MLX90393) -> bool:
    """Whether OFFSET_X/Y/Z still hold `mlx.OFFSET_TCMP_ZERO` when the chip's settings
    have TCMP_EN (then they are configuration too: three reads more a read-back, which
    `bound.cycle_bound` counts); True without TCMP_EN, reading nothing."""
    return (
        chip.settings is None
        or not chip.settings.tcmp_en
        or all(chip.read_register(reg) == mlx.OFFSET_TCMP_ZERO for reg in mlx.REG_OFFSETS)
    )


def _expected_registers(settings: mlx.Settings, conf1: int, conf2: int, conf3: int) -> dict[int, int]:
    """What CONF1..CONF3 must hold for ``settings``, other bits as read (`_expected_for`
    keeps it per chip: do not change the dict returned)."""
    return settings.to_registers({mlx.REG_CONF1: conf1, mlx.REG_CONF2: conf2, mlx.REG_CONF3: conf3})


def _rm_reply_len(zyxt: int) -> int:
    """Bytes of an RM reply: the status byte and two per selected item."""
    return 1 + 2 * len(mlx.zyxt_items(zyxt))


def bus_error(address: int, command: bytes, exc: OSError) -> ChipNotRespondingError:
    """The error of ``command`` to ``address`` failing on the bus with ``exc`` (a NACK, an I/O error)."""
    name = mlx.COMMAND_NAMES.get(command[0] & 0xF0, f"0x{command[0]:02X}")
    return ChipNotRespondingError(address, f"{name} failed on the bus: {exc.strerror or exc}", exc.errno)
