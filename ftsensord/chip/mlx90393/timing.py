"""The MLX90393's conversion times (single and burst), its waits after EX and RT, the
forbidden (OSR, DIG_FILT) combinations and the noise estimate that follows the conversion time."""

from __future__ import annotations

import math

from ftsensord.chip.mlx90393.protocol import ZYXT_T, axis_count

# --- Timing (nominal; the chip's oscillator varies by about +-20 %) ---------------
#: The slowest a chip's conversions may run, times nominal (the oscillator's +20 %): what a
#: driver waits for, and what the emulator runs at unless told otherwise.
OSCILLATOR_SLOWEST = 1.2
TSTBY_US = 220.0
TACTIVE_US = 360.0
TCONV_END_US = 100.0
#: BURST_DATA_RATE step on the low-power oscillator (+-5 %).
BURST_RATE_STEP_US = 20_000.0
#: Waits around a reset: after EX, and after RT before the next command.
T_AFTER_EX_US = 1_000.0
T_AFTER_RT_US = 1_500.0
#: HS (memory store) needs at least 15 ms.
T_HS_US = 15_000.0

#: Reading noise, an ESTIMATE to be replaced by a table measured on a real board: the
#: datasheet gives noise only as curves against conversion time, and users report it
#: follows TCONVM, not how OSR and DIG_FILT split it: RMS sigma = 2.0 uT sqrt(835 us /
#: TCONVM) on X and Y, 1.5 times that on Z. These values live here and nowhere else.
NOISE_REF_XY_UT = 2.0
NOISE_REF_TCONVM_US = 835.0
NOISE_Z_FACTOR = 1.5


def noise_ut(axis: str, tconvm_us: float) -> float:
    """RMS reading noise (uT) of one axis at a conversion time (the estimate above)."""
    sigma = NOISE_REF_XY_UT * math.sqrt(NOISE_REF_TCONVM_US / tconvm_us)
    return sigma * NOISE_Z_FACTOR if axis == "z" else sigma


#: Not permitted with HALLCONF 0xC; (1, 1) is reported by users, refused too.
FORBIDDEN_OSR_DIG_FILT = frozenset({(0, 0), (0, 1), (1, 0), (1, 1)})


def tconvm_us(osr: int, dig_filt: int) -> float:
    """Conversion time of one magnetic axis: 67 + 64 * 2**OSR * (2 + 2**DIG_FILT) us."""
    if not 0 <= osr <= 3:
        raise ValueError(f"OSR takes 0..3, got {osr!r}")
    if not 0 <= dig_filt <= 7:
        raise ValueError(f"DIG_FILT takes 0..7, got {dig_filt!r}")
    return 67.0 + 64.0 * 2**osr * (2 + 2**dig_filt)


def tconvt_us(osr2: int) -> float:
    """Conversion time of the temperature: 67 + 192 * 2**OSR2 us."""
    if not 0 <= osr2 <= 3:
        raise ValueError(f"OSR2 takes 0..3, got {osr2!r}")
    return 67.0 + 192.0 * 2**osr2


def conversion_us(zyxt: int, osr: int, dig_filt: int, osr2: int) -> float:
    """The conversions alone: m * TCONVM + (TCONVT if t) + TCONV_END, in us."""
    t = tconvt_us(osr2) if zyxt & ZYXT_T else 0.0
    return axis_count(zyxt) * tconvm_us(osr, dig_filt) + t + TCONV_END_US


def single_measurement_us(zyxt: int, osr: int, dig_filt: int, osr2: int) -> float:
    """Time from SM to data ready: TSTBY + TACTIVE + conversions, in us."""
    return TSTBY_US + TACTIVE_US + conversion_us(zyxt, osr, dig_filt, osr2)


def burst_interval_us(zyxt: int, osr: int, dig_filt: int, osr2: int, burst_data_rate: int) -> float:
    """Interval between burst-mode results, in us.

    BURST_DATA_RATE 0 converts back to back; n > 0 waits n * 20 ms, but never
    less than the conversions themselves take.
    """
    back_to_back = conversion_us(zyxt, osr, dig_filt, osr2)
    if burst_data_rate == 0:
        return back_to_back
    return max(back_to_back, burst_data_rate * BURST_RATE_STEP_US)
