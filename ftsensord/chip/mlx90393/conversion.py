"""From the MLX90393's data words to SI: sensitivity per GAIN_SEL, RES, HALLCONF and axis,
the data formats of every RES and TCMP_EN, saturation, temperature."""

from __future__ import annotations

from dataclasses import dataclass

from ftsensord.chip.mlx90393.protocol import TREF_TYPICAL
from ftsensord.errors import ForbiddenSettingError

# --- Sensitivity ---------------------------------------------------------------
#: uT/LSB at GAIN_SEL 7, RES 0, HALLCONF 0xC. X/Y is 6.009 / 40, the datasheet's
#: GAIN_SEL 0, RES 3 entry; its table prints 0.150, rounded.
SENS_BASE_XY_UT = 6.009 / 40
SENS_BASE_Z_UT = 0.242
#: Gain factor per GAIN_SEL (the datasheet prints 1.667 and 1.333 for 5/3 and 4/3).
GAIN_FACTOR = (5.0, 4.0, 3.0, 2.5, 2.0, 5.0 / 3.0, 4.0 / 3.0, 1.0)
#: HALLCONF 0x0 spins the Hall plates differently: sensitivity times 98/75.
HALLCONF_0_FACTOR = 98.0 / 75.0

#: The Hall element starts to saturate near 50 mT whatever the gain.
HALL_SATURATION_T = 50e-3
#: A reading this close to the element's limit is flagged saturated: the 1 mT
#: margin is far above the reading noise (a few uT plus one LSB, <10 uT), so a
#: clipped element is always caught, and far below any useful signal.
HALL_SATURATION_FLAG_T = HALL_SATURATION_T - 1e-3


def sensitivity_ut(gain_sel: int, res: int, axis: str, hallconf: int = 0xC) -> float:
    """Magnetic sensitivity in uT/LSB for one axis ('x', 'y' or 'z')."""
    if not 0 <= gain_sel <= 7:
        raise ValueError(f"GAIN_SEL takes 0..7, got {gain_sel!r}")
    if not 0 <= res <= 3:
        raise ValueError(f"RES takes 0..3, got {res!r}")
    if axis not in ("x", "y", "z"):
        raise ValueError(f"axis must be 'x', 'y' or 'z', got {axis!r}")
    if hallconf not in (0x0, 0xC):
        raise ValueError(f"sensitivity is documented for HALLCONF 0x0 and 0xC, got 0x{hallconf:X}")
    base = SENS_BASE_Z_UT if axis == "z" else SENS_BASE_XY_UT
    sens = base * GAIN_FACTOR[gain_sel] * 2**res
    return sens * HALLCONF_0_FACTOR if hallconf == 0x0 else sens


# --- Data format -----------------------------------------------------------------
@dataclass(frozen=True)
class RawFormat:
    """How a 16-bit magnetic word is coded for one (RES, TCMP_EN) pair.

    ``zero`` is the raw value of zero field (0 for signed words); ``span`` is the
    largest valid distance from it: a word at or past the span is saturated.
    """

    signed: bool
    zero: int
    span: int


def raw_format(res: int, tcmp_en: bool) -> RawFormat:
    """The coding of a magnetic word at resolution ``res`` with TCMP_EN on or off."""
    if tcmp_en:
        if res >= 2:
            raise ForbiddenSettingError(f"RES {res} is not allowed with TCMP_EN = 1 (only RES 0 and 1)")
        return RawFormat(signed=False, zero=32768, span=32767)
    if res in (0, 1):
        # Two's complement: -32768 and +32767 are the rails, so 32767 is the span.
        return RawFormat(signed=True, zero=0, span=32767)
    if res == 2:
        return RawFormat(signed=False, zero=32768, span=22000)
    if res == 3:
        return RawFormat(signed=False, zero=16384, span=11000)
    raise ValueError(f"RES takes 0..3, got {res!r}")


def raw_to_counts(word: int, fmt: RawFormat) -> int:
    """A 16-bit word (0..65535) as signed counts from zero field."""
    if not 0 <= word <= 0xFFFF:
        raise ValueError(f"a data word is 16 bits, got {word!r}")
    if fmt.signed:
        return word - 0x10000 if word & 0x8000 else word
    return word - fmt.zero


def counts_to_raw(counts: int, fmt: RawFormat) -> int:
    """Inverse of `raw_to_counts`, clamped to what 16 bits can hold."""
    if fmt.signed:
        return max(-32768, min(32767, counts)) & 0xFFFF
    return max(0, min(0xFFFF, counts + fmt.zero))


def is_saturated(counts: int, fmt: RawFormat) -> bool:
    """True when a reading is at or past the valid span: never a valid value."""
    return abs(counts) >= fmt.span


def raw_to_tesla(
    word: int, gain_sel: int, res: int, axis: str, *, tcmp_en: bool = False, hallconf: int = 0xC
) -> tuple[float, bool]:
    """Convert one magnetic word to tesla; returns (field_t, saturated)."""
    fmt = raw_format(res, tcmp_en)
    counts = raw_to_counts(word, fmt)
    return counts * sensitivity_ut(gain_sel, res, axis, hallconf) * 1e-6, is_saturated(counts, fmt)


#: Temperature scale: LSB per degC, and the reference temperature of TREF.
TEMP_LSB_PER_DEGC = 45.2
TEMP_AT_TREF_DEGC = 35.0


def raw_to_celsius(word: int, tref: int = TREF_TYPICAL) -> float:
    """Temperature in degC from the T word: 35 + (raw - TREF) / 45.2."""
    return TEMP_AT_TREF_DEGC + (word - tref) / TEMP_LSB_PER_DEGC


def celsius_to_raw(temp_c: float, tref: int = TREF_TYPICAL) -> int:
    """Inverse of `raw_to_celsius`, rounded and clamped to 16 bits."""
    return max(0, min(0xFFFF, round(tref + (temp_c - TEMP_AT_TREF_DEGC) * TEMP_LSB_PER_DEGC)))
