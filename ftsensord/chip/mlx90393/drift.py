"""The MLX90393's drift with temperature: sensitivity (with and without TCMP_EN) and offset.

Source: Melexis MLX90393 datasheet Rev 011 (Sep 2024): Table 9 (Magnetic Specification:
SENS_THD, OFFS_THD and their footnotes 7 and 9), Tables 17 and 18 (sensitivity in uT/LSB,
TC off, at 25 degC and at 35 degC). docs/design/physics.md ("Temperature") shows the arithmetic.
Every figure is per kelvin from `TEMPERATURE_REF_C`; tuples are per axis (x, y, z), where the
datasheet gives X/Y and Z apart.
"""

from __future__ import annotations

#: The die temperatures (degC) the parts are specified at: the MLX90393SLW this project names
#: (`PART_VARIANTS`), temperature code S, -20 to 85 degC. The datasheet's drifts say nothing
#: beyond; a scene, a dataset and a calibration file are held to it alike.
OPERATING_RANGE_C = (-20.0, 85.0)

#: The datasheet specifies the chip at 25 degC; every drift below is a change from there.
TEMPERATURE_REF_C = 25.0

#: Relative change of a reading (LSB per uT) per K with TCMP_EN = 0, typical, (x, y, z).
#: Tables 17 and 18 (TC off) give 6.009 -> 6.292 uT/LSB (X/Y) and 9.680 -> 10.137 (Z) at
#: GAIN_SEL 0, RES 3 from 25 to 35 degC: a reading falls by 4.50 % and 4.51 % over 10 K.
SENSITIVITY_TEMPCO_PER_K = (6.009 / 6.292 - 1) / 10.0, (6.009 / 6.292 - 1) / 10.0, (9.680 / 10.137 - 1) / 10.0

#: Part-to-part standard deviation of `SENSITIVITY_TEMPCO_PER_K` (per K, every axis). The
#: datasheet gives none for TC off; this is an assumption: the per-part trimmed compensation
#: factors (SENS_TC_HT/LT) exist because parts differ, and the compensated band they reach
#: (`SENSITIVITY_TEMPCO_TCMP_PER_K`) is taken as the spread of what they correct.
SENSITIVITY_TEMPCO_SPREAD_PER_K = 5.0e-4

#: Residual relative sensitivity drift per K with TCMP_EN = 1, as a BOUND (every axis): the
#: datasheet's SENS_THD is a band of +-3 % around the 25 degC sensitivity over the operating
#: range (footnote 9: a band, at wafer-level trimming); +-3 % over the 60 K from 25 to 85 degC
#: is +-5e-4 per K. A part lies anywhere in the band.
SENSITIVITY_TEMPCO_TCMP_PER_K = 3e-2 / 60.0

#: Offset drift at zero field, uT per K, (x, y, z), as a BOUND (TCMP_EN does not change it:
#: TCMP compensates sensitivity only). OFFS_THD is "< +-1000 LSB" from 25 degC over the range,
#: characterised at GAIN_SEL 7, RES 0 (0.150 uT/LSB X/Y, 0.242 Z; footnote 7), its steepest
#: near 85 degC: 1000 LSB over the 60 K from 25 to 85 degC, 2.50 and 4.03 uT/K.
OFFSET_DRIFT_UT_PER_K = 1000 * 0.150 / 60.0, 1000 * 0.150 / 60.0, 1000 * 0.242 / 60.0
