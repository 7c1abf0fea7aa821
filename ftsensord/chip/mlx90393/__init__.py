"""MLX90393 facts, in the datasheet's names, free of I/O: one face over five modules.

Opcodes, the zyxt nibble, the status byte, register fields, sensitivity,
raw-to-field conversion, temperature conversion, conversion times, the
forbidden (OSR, DIG_FILT) combinations and the drift with temperature
(`thermal`). Both the driver (`chip.driver`) and the emulated chip
(`sim.chip`) are written against this module, so the two cannot drift apart
on a fact.

Source: Melexis MLX90393 datasheet Rev 011, as summarised in the project's
reference notes. Units: fields in uT where a name says ``_ut`` and in tesla
(T) where it says ``_t``; times in microseconds where a name says ``_us``.
"""

from __future__ import annotations

from ftsensord.chip.mlx90393.conversion import GAIN_FACTOR, HALL_SATURATION_FLAG_T, HALL_SATURATION_T, HALLCONF_0_FACTOR, SENS_BASE_XY_UT, SENS_BASE_Z_UT, TEMP_AT_TREF_DEGC, TEMP_LSB_PER_DEGC, RawFormat, celsius_to_raw, counts_to_raw, is_saturated, raw_format, raw_to_celsius, raw_to_counts, raw_to_tesla, sensitivity_ut
from ftsensord.chip.mlx90393.protocol import ADDRESS_MAX, ADDRESS_MIN, BIST, BURST_DATA_RATE, BURST_SEL, CMD_EX, CMD_HR, CMD_HS, CMD_NOP, CMD_RM, CMD_RR, CMD_RT, CMD_SB, CMD_SM, CMD_SW, CMD_WR, COMM_MODE, COMMAND_NAMES, DIG_FILT, EXT_TRIG, GAIN_SEL, HALLCONF, ITEM_ORDER, OFFSET_TCMP_ZERO, OSR, OSR2, PART_VARIANTS, POWER_ON_DEFAULTS, REG_CONF1, REG_CONF2, REG_CONF3, REG_CUSTOMER_MAX, REG_MAX, REG_OFFSET_X, REG_OFFSET_Y, REG_OFFSET_Z, REG_OFFSETS, REG_SENS_TC, REG_TREF, REG_WOT_THRESHOLD, REG_WOXY_THRESHOLD, REG_WOZ_THRESHOLD, RES_X, RES_Y, RES_Z, STATUS_BURST_MODE, STATUS_D_MASK, STATUS_ERROR, STATUS_RS, STATUS_SED, STATUS_SM_MODE, STATUS_WOC_MODE, STATUSES, TCMP_EN, TREF_TYPICAL, TRIG_INT_SEL, WOC_DIFF, Z_SERIES, ZYXT_T, ZYXT_X, ZYXT_XYZ, ZYXT_XYZT, ZYXT_Y, ZYXT_Z, Field, Status, axis_count, d_for_items, items_zyxt, part_variant, status_of, zyxt_items
from ftsensord.chip.mlx90393.settings import Settings
from ftsensord.chip.mlx90393.drift import OFFSET_DRIFT_UT_PER_K, OPERATING_RANGE_C, SENSITIVITY_TEMPCO_PER_K, SENSITIVITY_TEMPCO_SPREAD_PER_K, SENSITIVITY_TEMPCO_TCMP_PER_K, TEMPERATURE_REF_C
from ftsensord.chip.mlx90393.timing import BURST_RATE_STEP_US, FORBIDDEN_OSR_DIG_FILT, NOISE_REF_TCONVM_US, NOISE_REF_XY_UT, NOISE_Z_FACTOR, OSCILLATOR_SLOWEST, T_AFTER_EX_US, T_AFTER_RT_US, T_HS_US, TACTIVE_US, TCONV_END_US, TSTBY_US, burst_interval_us, conversion_us, noise_ut, single_measurement_us, tconvm_us, tconvt_us
