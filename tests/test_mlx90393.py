"""The datasheet module against the datasheet's own numbers."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from ftsensord.chip import mlx90393 as mlx
from ftsensord.errors import ForbiddenSettingError

# Datasheet sensitivity table, HALLCONF 0xC, RES 0 column: (X/Y, Z) in uT/LSB per GAIN_SEL.
DATASHEET_RES0 = [
    (0.751, 1.210),
    (0.601, 0.968),
    (0.451, 0.726),
    (0.376, 0.605),
    (0.300, 0.484),
    (0.250, 0.403),
    (0.200, 0.323),
    (0.150, 0.242),
]


@pytest.mark.parametrize(("gain_sel", "res", "xy", "z"), [(0, 3, 6.009, 9.680), (7, 0, 0.150, 0.242)])
def test_sensitivity_matches_the_datasheet_and_the_paper(gain_sel, res, xy, z):
    assert round(mlx.sensitivity_ut(gain_sel, res, "x"), 3) == xy
    assert round(mlx.sensitivity_ut(gain_sel, res, "y"), 3) == xy
    assert round(mlx.sensitivity_ut(gain_sel, res, "z"), 3) == z


@pytest.mark.parametrize("gain_sel", range(8))
def test_sensitivity_rule_reproduces_the_datasheet_table(gain_sel):
    xy, z = DATASHEET_RES0[gain_sel]
    assert round(mlx.sensitivity_ut(gain_sel, 0, "x"), 3) == xy
    assert round(mlx.sensitivity_ut(gain_sel, 0, "z"), 3) == z
    for res in range(4):  # each RES step doubles the LSB
        assert mlx.sensitivity_ut(gain_sel, res, "z") == pytest.approx(z * 2**res, abs=0.0005 * 2**res)


def test_hallconf_0_scales_sensitivity_by_98_over_75():
    assert mlx.sensitivity_ut(7, 0, "x", 0x0) / mlx.sensitivity_ut(7, 0, "x") == pytest.approx(98 / 75)


@pytest.mark.parametrize("bad", [dict(gain_sel=8), dict(res=4), dict(axis="t"), dict(hallconf=0x5)])
def test_sensitivity_refuses_values_out_of_range(bad):
    args = dict(gain_sel=0, res=0, axis="x", hallconf=0xC) | bad
    with pytest.raises(ValueError):
        mlx.sensitivity_ut(**args)


def test_tconvm_is_835_us_at_the_papers_settings():
    assert mlx.tconvm_us(1, 2) == 835.0
    assert mlx.tconvm_us(2, 0) == 835.0  # the other split with the same time
    assert mlx.tconvm_us(0, 2) == 67 + 64 * 6
    assert mlx.tconvm_us(3, 7) == 67 + 64 * 8 * 130


def test_the_papers_3_34_ms_is_preparation_plus_three_axes():
    # The paper's "839 us preparation" is TSTBY + TACTIVE + TCONVT(OSR2 0):
    prep = mlx.TSTBY_US + mlx.TACTIVE_US + mlx.tconvt_us(0)
    assert prep == 839.0
    assert prep + 3 * mlx.tconvm_us(1, 2) == pytest.approx(3340, abs=5)
    # The full formula adds TCONV_END, which the paper's figure leaves out.
    assert mlx.single_measurement_us(mlx.ZYXT_XYZT, 1, 2, 0) == 839 + 3 * 835 + 100
    assert mlx.single_measurement_us(mlx.ZYXT_XYZ, 1, 2, 0) == 220 + 360 + 3 * 835 + 100


def test_burst_interval_back_to_back_and_on_the_slow_oscillator():
    assert mlx.burst_interval_us(mlx.ZYXT_XYZ, 1, 2, 0, 0) == 3 * 835 + 100
    assert mlx.burst_interval_us(mlx.ZYXT_XYZ, 1, 2, 0, 5) == 100_000
    # Never faster than the conversions themselves:
    assert mlx.burst_interval_us(mlx.ZYXT_XYZ, 3, 7, 0, 1) == 3 * mlx.tconvm_us(3, 7) + 100


@pytest.mark.parametrize(("osr", "dig_filt"), sorted(mlx.FORBIDDEN_OSR_DIG_FILT))
def test_forbidden_osr_dig_filt_combinations_are_refused(osr, dig_filt):
    with pytest.raises(ForbiddenSettingError, match=f"OSR {osr} with DIG_FILT {dig_filt}"):
        mlx.Settings(osr=osr, dig_filt=dig_filt).validate()


def test_every_other_osr_dig_filt_combination_is_accepted():
    allowed = [(o, d) for o in range(4) for d in range(8) if (o, d) not in mlx.FORBIDDEN_OSR_DIG_FILT]
    assert len(allowed) == 28
    for osr, dig_filt in allowed:
        mlx.Settings(osr=osr, dig_filt=dig_filt).validate()


def test_settings_refuse_tcmp_with_res_2_or_3_and_out_of_range_fields():
    with pytest.raises(ForbiddenSettingError, match="TCMP_EN"):
        mlx.Settings(tcmp_en=True, res_x=0, res_y=0, res_z=2).validate()
    mlx.Settings(tcmp_en=True, res_x=1, res_y=0, res_z=1).validate()
    with pytest.raises(ForbiddenSettingError, match="GAIN_SEL takes 0..7"):
        mlx.Settings(gain_sel=9).validate()
    with pytest.raises(ForbiddenSettingError, match="HALLCONF"):
        mlx.Settings(hallconf=0x3).validate()


# --- raw word decoding, every RES and TCMP_EN form ----------------------------------
@pytest.mark.parametrize(
    ("res", "tcmp", "word", "counts"),
    [
        (0, False, 0x0000, 0),
        (0, False, 0x7FFF, 32767),
        (0, False, 0x8000, -32768),
        (0, False, 0xFFFF, -1),
        (1, False, 0x0010, 16),
        (1, False, 0xFFF0, -16),
        (2, False, 32768, 0),
        (2, False, 32768 + 21999, 21999),
        (2, False, 32768 - 22000, -22000),
        (3, False, 16384, 0),
        (3, False, 16384 + 10999, 10999),
        (3, False, 16384 - 11000, -11000),
        (0, True, 32768, 0),
        (0, True, 0, -32768),
        (1, True, 40000, 40000 - 32768),
    ],
)
def test_raw_words_decode_per_res_and_tcmp(res, tcmp, word, counts):
    assert mlx.raw_to_counts(word, mlx.raw_format(res, tcmp)) == counts


@pytest.mark.parametrize(("res", "span"), [(0, 32767), (1, 32767), (2, 22000), (3, 11000)])
def test_a_value_at_or_past_the_span_is_saturated_one_inside_is_not(res, span):
    fmt = mlx.raw_format(res, False)
    assert not mlx.is_saturated(span - 1, fmt) and not mlx.is_saturated(-(span - 1), fmt)
    assert mlx.is_saturated(span, fmt) and mlx.is_saturated(-span, fmt)
    assert mlx.is_saturated(span + 1, fmt)


@pytest.mark.parametrize("res", [2, 3])
def test_tcmp_en_forbids_res_2_and_3(res):
    with pytest.raises(ForbiddenSettingError):
        mlx.raw_format(res, True)


def test_raw_to_tesla_uses_the_papers_lsb_and_flags_saturation():
    # RES 3: zero at 16384; 100 LSB above zero on Z at GAIN_SEL 0 is 968 uT.
    value, sat = mlx.raw_to_tesla(16384 + 100, 0, 3, "z")
    assert value == pytest.approx(968e-6, rel=1e-4) and not sat
    value, sat = mlx.raw_to_tesla(16384 - 11000, 0, 3, "x")
    assert value == pytest.approx(-11000 * 6.009e-6, rel=1e-4) and sat


@given(
    st.sampled_from([(0, False), (1, False), (2, False), (3, False), (0, True), (1, True)]),
    st.integers(-40000, 40000),
)
def test_counts_round_trip_within_16_bits_and_clamp_outside(form, counts):
    fmt = mlx.raw_format(*form)
    word = mlx.counts_to_raw(counts, fmt)
    assert 0 <= word <= 0xFFFF
    back = mlx.raw_to_counts(word, fmt)
    low = -32768 if fmt.signed else -fmt.zero
    high = 32767 if fmt.signed else 0xFFFF - fmt.zero
    assert back == min(high, max(low, counts))


def test_temperature_conversion_both_datasheet_forms():
    assert mlx.raw_to_celsius(46244) == pytest.approx(25.0)
    assert mlx.raw_to_celsius(mlx.TREF_TYPICAL) == 35.0
    assert mlx.raw_to_celsius(46244 + 452) == pytest.approx(35.0)
    assert mlx.raw_to_celsius(46296, tref=46296 + 452) == pytest.approx(25.0)
    assert mlx.raw_to_celsius(mlx.celsius_to_raw(61.3)) == pytest.approx(61.3, abs=1 / 45.2)


# --- status byte, registers, zyxt, addresses ----------------------------------------
def test_status_byte_fields():
    s = mlx.Status(0b1011_0110)
    assert (s.burst_mode, s.woc_mode, s.sm_mode, s.error, s.sed, s.rs) == (
        True,
        False,
        True,
        True,
        False,
        True,
    )
    assert s.d == 2 and s.data_bytes == 6
    assert mlx.Status(0x03).data_bytes == 8 and mlx.Status(0x00).data_bytes == 2
    assert "ERROR" in str(s) and "BURST_MODE" in str(s)


def test_register_fields_sit_at_the_datasheets_bit_positions():
    assert mlx.GAIN_SEL.mask == 0x0070 and mlx.HALLCONF.mask == 0x000F
    assert mlx.TCMP_EN.mask == 0x0400 and mlx.BURST_SEL.mask == 0x03C0 and mlx.BURST_DATA_RATE.mask == 0x003F
    assert mlx.OSR2.mask == 0x1800 and mlx.RES_Z.mask == 0x0600 and mlx.RES_Y.mask == 0x0180
    assert mlx.RES_X.mask == 0x0060 and mlx.DIG_FILT.mask == 0x001C and mlx.OSR.mask == 0x0003
    assert mlx.POWER_ON_DEFAULTS[mlx.REG_CONF1] == 0x007C  # GAIN_SEL 7, HALLCONF 0xC
    with pytest.raises(ValueError):
        mlx.OSR.set(0, 4)


def test_settings_round_trip_through_registers_and_keep_reserved_bits():
    s = mlx.Settings(
        gain_sel=3,
        res_x=1,
        res_y=2,
        res_z=3,
        osr=2,
        dig_filt=5,
        osr2=1,
        burst_sel=mlx.ZYXT_XYZT,
        burst_data_rate=7,
    )
    regs = s.to_registers({mlx.REG_CONF1: 0xFE00 | 0x007C, mlx.REG_CONF2: 0, mlx.REG_CONF3: 0xE000})
    assert regs[mlx.REG_CONF1] & 0xFE00 == 0xFE00  # reserved bits kept as read
    assert regs[mlx.REG_CONF3] & 0xE000 == 0xE000
    assert mlx.Settings.from_registers(regs) == s


def test_zyxt_items_come_in_rm_order():
    assert mlx.zyxt_items(mlx.ZYXT_XYZT) == ("t", "x", "y", "z")
    assert mlx.zyxt_items(0b1010) == ("x", "z")
    assert mlx.items_zyxt(("z", "t")) == 0b1001
    assert mlx.axis_count(mlx.ZYXT_XYZT) == 3
    with pytest.raises(ValueError):
        mlx.zyxt_items(0x10)


@pytest.mark.parametrize(
    ("address", "code"),
    [(0x0C, "011"), (0x0F, "011"), (0x10, "012"), (0x17, "013"), (0x18, "014"), (0x1B, "014")],
)
def test_part_variant_from_address(address, code):
    assert mlx.part_variant(address) == f"MLX90393SLW-ABA-{code}"


@pytest.mark.parametrize("address", [0x0B, 0x1C, 0x50])
def test_part_variant_refuses_other_addresses(address):
    with pytest.raises(ValueError, match="0x0C-0x1B"):
        mlx.part_variant(address)
