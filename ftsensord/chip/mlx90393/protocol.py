"""The MLX90393's I2C protocol in the datasheet's names: commands, the zyxt nibble,
the status byte, registers and their fields, power-on defaults, addresses and part variants."""

from __future__ import annotations

from dataclasses import dataclass

# --- Commands (first byte; the low nibble of SB/SW/SM/RM is zyxt) -----------------
CMD_NOP = 0x00  # no operation: Melexis's own driver (MLX90393_CMD_NOP), status only
CMD_SB = 0x10  # start burst mode
CMD_SW = 0x20  # start wake-on-change mode
CMD_SM = 0x30  # start single measurement
CMD_RM = 0x40  # read measurement
CMD_RR = 0x50  # read register
CMD_WR = 0x60  # write register
CMD_EX = 0x80  # exit mode
CMD_HR = 0xD0  # memory recall (non-volatile -> RAM)
CMD_HS = 0xE0  # memory store (RAM -> non-volatile)
CMD_RT = 0xF0  # reset

COMMAND_NAMES = {
    CMD_NOP: "NOP",
    CMD_SB: "SB",
    CMD_SW: "SW",
    CMD_SM: "SM",
    CMD_RM: "RM",
    CMD_RR: "RR",
    CMD_WR: "WR",
    CMD_EX: "EX",
    CMD_HR: "HR",
    CMD_HS: "HS",
    CMD_RT: "RT",
}

# --- zyxt nibble ---------------------------------------------------------------
ZYXT_T = 0x1
ZYXT_X = 0x2
ZYXT_Y = 0x4
ZYXT_Z = 0x8
ZYXT_XYZ = ZYXT_X | ZYXT_Y | ZYXT_Z
ZYXT_XYZT = ZYXT_XYZ | ZYXT_T

#: Order in which RM returns the selected items (and the chip converts them).
ITEM_ORDER = ("t", "x", "y", "z")
_ITEM_BIT = {"t": ZYXT_T, "x": ZYXT_X, "y": ZYXT_Y, "z": ZYXT_Z}
#: Each nibble's items, worked out once: every command of every cycle asks.
_ITEMS = tuple(tuple(item for item in ITEM_ORDER if zyxt & _ITEM_BIT[item]) for zyxt in range(16))


def zyxt_items(zyxt: int) -> tuple[str, ...]:
    """The items a zyxt nibble selects, in the order RM returns them (T, X, Y, Z)."""
    if not 0 <= zyxt <= 0xF:
        raise ValueError(f"zyxt must be a 4-bit nibble, got {zyxt!r}")
    return _ITEMS[zyxt]


def items_zyxt(items: tuple[str, ...]) -> int:
    """The zyxt nibble that selects ``items`` (inverse of `zyxt_items`)."""
    return sum(_ITEM_BIT[item] for item in set(items))


def axis_count(zyxt: int) -> int:
    """Number of magnetic axes (X, Y, Z) a zyxt nibble selects."""
    return sum(1 for item in zyxt_items(zyxt) if item != "t")


# --- Status byte ---------------------------------------------------------------
STATUS_BURST_MODE = 0x80
STATUS_WOC_MODE = 0x40
STATUS_SM_MODE = 0x20
STATUS_ERROR = 0x10
STATUS_SED = 0x08
STATUS_RS = 0x04
STATUS_D_MASK = 0x03


@dataclass(frozen=True)
class Status:
    """A decoded status byte (the first byte of every reply)."""

    byte: int

    @property
    def burst_mode(self) -> bool:
        return bool(self.byte & STATUS_BURST_MODE)

    @property
    def woc_mode(self) -> bool:
        return bool(self.byte & STATUS_WOC_MODE)

    @property
    def sm_mode(self) -> bool:
        return bool(self.byte & STATUS_SM_MODE)

    @property
    def error(self) -> bool:
        return bool(self.byte & STATUS_ERROR)

    @property
    def sed(self) -> bool:
        """A single-bit memory error was corrected (information only)."""
        return bool(self.byte & STATUS_SED)

    @property
    def rs(self) -> bool:
        """Set in the reply to RT (reset)."""
        return bool(self.byte & STATUS_RS)

    @property
    def d(self) -> int:
        """D1:D0."""
        return self.byte & STATUS_D_MASK

    @property
    def data_bytes(self) -> int:
        """Number of data bytes that follow the status byte after RR or RM: 2*D + 2."""
        return 2 * self.d + 2

    def __str__(self) -> str:
        flags = [
            name
            for name, on in (
                ("BURST_MODE", self.burst_mode),
                ("WOC_MODE", self.woc_mode),
                ("SM_MODE", self.sm_mode),
                ("ERROR", self.error),
                ("SED", self.sed),
                ("RS", self.rs),
            )
            if on
        ]
        return f"0x{self.byte:02X} [{' '.join(flags) or 'idle'} D={self.d}]"


#: Every status byte's `Status`, made once: it is frozen, so sharing is safe and a cycle
#: builds none.
STATUSES = tuple(Status(b) for b in range(256))


def status_of(byte: int) -> Status:
    """The `Status` of ``byte`` (0-255), from `STATUSES`."""
    return STATUSES[byte]


def d_for_items(n_items: int) -> int:
    """D1:D0 for a reply of ``n_items`` 16-bit words (2*D + 2 = 2*n_items)."""
    if not 1 <= n_items <= 4:
        raise ValueError(f"a reply holds 1 to 4 words, got {n_items}")
    return n_items - 1


# --- Registers -----------------------------------------------------------------
REG_CONF1 = 0x00
REG_CONF2 = 0x01
REG_CONF3 = 0x02
REG_SENS_TC = 0x03
REG_OFFSET_X = 0x04
REG_OFFSET_Y = 0x05
REG_OFFSET_Z = 0x06
REG_WOXY_THRESHOLD = 0x07
REG_WOZ_THRESHOLD = 0x08
REG_WOT_THRESHOLD = 0x09
REG_TREF = 0x24

REG_OFFSETS = (REG_OFFSET_X, REG_OFFSET_Y, REG_OFFSET_Z)
#: OFFSET_X/Y/Z for TCMP_EN = 1: the compensated output is referenced to these registers,
#: so zero field reads 0x8000 (the coding `raw_format` assumes) only when they hold 0x8000;
#: their power-on 0 gives garbage (Melexis's application note on TCMP; tedyapo/
#: arduino-MLX90393 issue 26: "offsets have to be programmed relative to 0x8000").
OFFSET_TCMP_ZERO = 0x8000

#: Largest register address: RR/WR send ``reg << 2`` in one byte.
REG_MAX = 0x3F
#: The customer area; above it lies the Melexis area (read only, holds TREF).
REG_CUSTOMER_MAX = 0x1F

#: TREF's typical value (datasheet: temperature reference, read only).
TREF_TYPICAL = 0xB668


@dataclass(frozen=True)
class Field:
    """A bit field of a 16-bit register: ``width`` bits starting at bit ``lsb``."""

    name: str
    reg: int
    lsb: int
    width: int

    @property
    def mask(self) -> int:
        return ((1 << self.width) - 1) << self.lsb

    @property
    def max(self) -> int:
        return (1 << self.width) - 1

    def get(self, word: int) -> int:
        return (word & self.mask) >> self.lsb

    def set(self, word: int, value: int) -> int:
        if not 0 <= value <= self.max:
            raise ValueError(f"{self.name} takes 0..{self.max}, got {value!r}")
        return (word & ~self.mask & 0xFFFF) | (value << self.lsb)


BIST = Field("BIST", REG_CONF1, 8, 1)
Z_SERIES = Field("Z_SERIES", REG_CONF1, 7, 1)
GAIN_SEL = Field("GAIN_SEL", REG_CONF1, 4, 3)
HALLCONF = Field("HALLCONF", REG_CONF1, 0, 4)

TRIG_INT_SEL = Field("TRIG_INT_SEL", REG_CONF2, 15, 1)
COMM_MODE = Field("COMM_MODE", REG_CONF2, 13, 2)
WOC_DIFF = Field("WOC_DIFF", REG_CONF2, 12, 1)
EXT_TRIG = Field("EXT_TRIG", REG_CONF2, 11, 1)
TCMP_EN = Field("TCMP_EN", REG_CONF2, 10, 1)
BURST_SEL = Field("BURST_SEL", REG_CONF2, 6, 4)
BURST_DATA_RATE = Field("BURST_DATA_RATE", REG_CONF2, 0, 6)

OSR2 = Field("OSR2", REG_CONF3, 11, 2)
RES_Z = Field("RES_Z", REG_CONF3, 9, 2)
RES_Y = Field("RES_Y", REG_CONF3, 7, 2)
RES_X = Field("RES_X", REG_CONF3, 5, 2)
DIG_FILT = Field("DIG_FILT", REG_CONF3, 2, 3)
OSR = Field("OSR", REG_CONF3, 0, 2)

#: Power-on (and post-RT) register values: GAIN_SEL = 7, HALLCONF = 0xC, all else 0.
POWER_ON_DEFAULTS = {REG_CONF1: GAIN_SEL.set(HALLCONF.set(0, 0xC), 7)}

# --- Addresses -------------------------------------------------------------------
ADDRESS_MIN = 0x0C
ADDRESS_MAX = 0x1B

#: Part variant by the address range its EE_I2C_ADDR[4:0] gives.
PART_VARIANTS = (
    (0x0C, 0x0F, "MLX90393SLW-ABA-011"),
    (0x10, 0x13, "MLX90393SLW-ABA-012"),
    (0x14, 0x17, "MLX90393SLW-ABA-013"),
    (0x18, 0x1B, "MLX90393SLW-ABA-014"),
)


def part_variant(address: int) -> str:
    """The ordering code whose address range holds ``address``."""
    for low, high, name in PART_VARIANTS:
        if low <= address <= high:
            return name
    raise ValueError(f"0x{address:02X} is not an MLX90393 address (0x0C-0x1B)")
