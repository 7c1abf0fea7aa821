"""Every command round-trips through the emulated chip, refusals included."""

from __future__ import annotations

import errno

import numpy as np
import pytest
from smbus2 import i2c_msg

from ftsensord.chip import mlx90393 as mlx
from ftsensord.chip.driver import MLX90393
from ftsensord.errors import ChipNotRespondingError, ChipRefusedError
from ftsensord.sim import NoiseModel, StaticScene, VirtualClock, simulated_bus

from .conftest import ADDR


def xfer(bus, command: bytes, n: int, address: int = ADDR) -> bytes:
    """One raw command: write, repeated start, read n bytes."""
    w, r = i2c_msg.write(address, command), i2c_msg.read(address, n)
    bus.i2c_rdwr(w, r)
    return bytes(r)


def status(bus, command: bytes, n: int = 1) -> mlx.Status:
    return mlx.Status(xfer(bus, command, n)[0])


def configure_raw(bus, settings: mlx.Settings = mlx.Settings()) -> None:
    for reg, value in settings.to_registers().items():
        assert not status(bus, bytes([mlx.CMD_WR, value >> 8, value & 0xFF, reg << 2])).error


SM_NOMINAL_S = mlx.Settings().single_measurement_us() * 1e-6
#: The emulated chips run at the slowest the datasheet allows unless told otherwise.
SM_XYZ_S = SM_NOMINAL_S * mlx.OSCILLATOR_SLOWEST


# --- power-on, registers ------------------------------------------------------------
def test_power_on_registers_and_tref(bus):
    for reg, expected in ((0x00, 0x007C), (0x01, 0), (0x02, 0), (0x24, mlx.TREF_TYPICAL)):
        reply = xfer(bus, bytes([mlx.CMD_RR, reg << 2]), 3)
        assert mlx.Status(reply[0]) == mlx.Status(0x00)  # idle, no error, D=0 (two bytes follow)
        assert (reply[1] << 8) | reply[2] == expected


def test_write_then_read_register(bus):
    # Idle, no error; D1:D0 1 or 2 as real chips answer WR (meaningless after WR).
    assert status(bus, bytes([mlx.CMD_WR, 0x12, 0x34, 0x04 << 2])).byte in (0x01, 0x02)
    assert xfer(bus, bytes([mlx.CMD_RR, 0x04 << 2]), 3)[1:] == b"\x12\x34"


@pytest.mark.parametrize(
    "command",
    [
        bytes([mlx.CMD_WR, 0, 1, mlx.REG_TREF << 2]),  # Melexis area is read only
        bytes([mlx.CMD_WR, 0, 1, (0x02 << 2) | 1]),  # malformed address byte
        bytes([mlx.CMD_RR, (0x02 << 2) | 2]),
        bytes([mlx.CMD_RR]),  # missing address byte
        bytes([mlx.CMD_WR, 0, 1]),
    ],
)
def test_register_address_out_of_range_or_malformed_is_refused(bus, command):
    assert status(bus, command).error


def test_unknown_opcode_is_refused(bus):
    assert status(bus, bytes([0x70])).error  # Adafruit's wrong "HS"
    assert status(bus, bytes([0x0F])).error and status(bus, bytes([0x00, 0x00])).error  # not NOP


def test_nop_returns_the_status_and_changes_nothing(bus):
    """NOP (0x00) is in the datasheet's command list (Melexis's driver: MLX90393_CMD_NOP):
    accepted in any mode, with the mode bits as they are, a conversion under way untouched."""
    s = status(bus, bytes([mlx.CMD_NOP]))
    assert not s.error and not (s.sm_mode or s.burst_mode)
    configure_raw(bus)
    assert status(bus, bytes([mlx.CMD_SM | mlx.ZYXT_XYZ])).sm_mode
    s = status(bus, bytes([mlx.CMD_NOP]))
    assert not s.error and s.sm_mode
    bus.sleep(SM_XYZ_S)
    assert not mlx.Status(xfer(bus, bytes([mlx.CMD_RM | mlx.ZYXT_XYZ]), 7)[0]).error
    assert status(bus, bytes([mlx.CMD_SB | mlx.ZYXT_XYZ])).burst_mode
    s = status(bus, bytes([mlx.CMD_NOP]))
    assert not s.error and s.burst_mode
    bus.chips[ADDR].memory_error = True  # then only RT is accepted
    assert status(bus, bytes([mlx.CMD_NOP])).error


def test_memory_recall_and_store(bus):
    chip = bus.chips[ADDR]
    assert not status(bus, bytes([mlx.CMD_WR, 0x00, 0x01, 0x01 << 2])).error
    assert not status(bus, bytes([mlx.CMD_HR])).error  # recall overwrites RAM with NV
    assert chip.registers[0x01] == 0
    assert not status(bus, bytes([mlx.CMD_WR, 0x00, 0x05, 0x01 << 2])).error
    assert not status(bus, bytes([mlx.CMD_HS])).error
    assert chip.nonvolatile[0x01] == 5
    with pytest.raises(OSError):  # busy storing for 15 ms: no ACK
        status(bus, bytes([mlx.CMD_EX]))
    bus.sleep(mlx.T_HS_US * 1e-6)
    assert not status(bus, bytes([mlx.CMD_EX])).error
    chip.power_on()
    assert chip.registers[0x01] == 5  # power-on loads what HS stored


# --- reset ----------------------------------------------------------------------------
def test_reset_sets_rs_restores_defaults_and_nacks_during_its_wait(bus):
    configure_raw(bus)
    s = status(bus, bytes([mlx.CMD_RT]))
    assert s.rs and not s.error
    with pytest.raises(OSError) as exc:  # within the 1.5 ms the chip does not answer
        status(bus, bytes([mlx.CMD_EX]))
    assert exc.value.errno == errno.EREMOTEIO  # i2c-bcm2835's word for a NACK (the default adapter)
    bus.sleep(mlx.T_AFTER_RT_US * 1e-6)
    assert not status(bus, bytes([mlx.CMD_EX])).error
    assert xfer(bus, bytes([mlx.CMD_RR, 0x02 << 2]), 3)[1:] == b"\x00\x00"


def test_rt_alone_does_not_leave_burst_but_the_drivers_reset_does(bus):
    configure_raw(bus)
    assert status(bus, bytes([mlx.CMD_SB | mlx.ZYXT_XYZ])).burst_mode
    bus.sleep(0.01)
    assert status(bus, bytes([mlx.CMD_RT])).burst_mode  # quirk: still bursting
    bus.sleep(0.002)
    drv = MLX90393(bus, ADDR, sleep=bus.sleep)
    s = drv.reset()
    assert s.rs and not s.burst_mode
    assert not drv.exit_mode().burst_mode


def test_memory_error_refuses_everything_but_rt(bus):
    bus.chips[ADDR].memory_error = True
    for command in (bytes([mlx.CMD_EX]), bytes([mlx.CMD_RR, 0]), bytes([mlx.CMD_SM | 0xE])):
        assert status(bus, command).error
    assert not status(bus, bytes([mlx.CMD_RT])).error
    bus.sleep(0.002)
    assert not status(bus, bytes([mlx.CMD_EX])).error


# --- single measurement --------------------------------------------------------------
def test_single_measurement_timing_data_ready_and_return_to_idle(bus):
    configure_raw(bus)
    s = status(bus, bytes([mlx.CMD_SM | mlx.ZYXT_XYZ]))
    assert s.sm_mode and not s.error
    bus.sleep(SM_XYZ_S - 200e-6)  # the RM itself takes ~40 us of bus time at most
    early = xfer(bus, bytes([mlx.CMD_RM | mlx.ZYXT_XYZ]), 7)
    assert mlx.Status(early[0]).error and mlx.Status(early[0]).sm_mode  # data not ready
    bus.sleep(200e-6)
    reply = xfer(bus, bytes([mlx.CMD_RM | mlx.ZYXT_XYZ]), 7)
    s = mlx.Status(reply[0])
    assert not s.error and not s.sm_mode and s.data_bytes == 6
    again = xfer(bus, bytes([mlx.CMD_RM | mlx.ZYXT_XYZ]), 7)
    assert mlx.Status(again[0]).error  # DRDY low once read


@pytest.mark.parametrize("oscillator", [0.8, 1.2])  # the datasheet's +-20 %
def test_a_chip_whose_oscillator_runs_off_nominal_has_its_data_that_much_sooner_or_later(bus, oscillator):
    """An outside driver waiting the nominal conversion time, no margin, read its data here on
    every chip (2026-11-27); a chip at the slow end of the datasheet's +-20 % refuses that RM."""
    bus.chips[ADDR].oscillator = oscillator
    configure_raw(bus)
    assert not status(bus, bytes([mlx.CMD_SM | mlx.ZYXT_XYZ])).error
    bus.sleep(SM_NOMINAL_S * oscillator - 50e-6)
    assert mlx.Status(xfer(bus, bytes([mlx.CMD_RM | mlx.ZYXT_XYZ]), 7)[0]).error  # not ready yet
    bus.sleep(100e-6)
    assert not mlx.Status(xfer(bus, bytes([mlx.CMD_RM | mlx.ZYXT_XYZ]), 7)[0]).error


def test_an_sm_whose_status_is_not_read_measures_nothing(bus):
    """The datasheet: the first SM after power-up or reset should have its status read
    back to get valid data. The emulator starts no SM whose status the next command
    overtakes (every SM: a chip may reset unseen): no data, the RM refused with SM_MODE
    clear, however long after; the chip takes the next SM."""
    configure_raw(bus)
    bus.i2c_rdwr(i2c_msg.write(ADDR, [mlx.CMD_SM | mlx.ZYXT_XYZ]))  # a write alone: status never read
    bus.sleep(2 * SM_XYZ_S)
    reply = mlx.Status(xfer(bus, bytes([mlx.CMD_RM | mlx.ZYXT_XYZ]), 7)[0])
    assert reply.error and not reply.sm_mode
    bus.i2c_rdwr(i2c_msg.write(ADDR, [mlx.CMD_SM | mlx.ZYXT_XYZ]))
    s = status(bus, bytes([mlx.CMD_SM | mlx.ZYXT_XYZ]))  # not refused as "SM while in SM"
    assert s.sm_mode and not s.error
    bus.sleep(SM_XYZ_S)
    assert not mlx.Status(xfer(bus, bytes([mlx.CMD_RM | mlx.ZYXT_XYZ]), 7)[0]).error


def test_an_sm_whose_status_is_read_in_an_ioctl_of_its_own_measures(bus):
    """Write, stop, then a read of the status on its own: the status is read (the
    reference: write+STOP then a separate read works on real chips)."""
    configure_raw(bus)
    bus.i2c_rdwr(i2c_msg.write(ADDR, [mlx.CMD_SM | mlx.ZYXT_XYZ]))
    r = i2c_msg.read(ADDR, 1)
    bus.i2c_rdwr(r)
    assert mlx.Status(bytes(r)[0]).sm_mode
    bus.sleep(SM_XYZ_S)
    assert not mlx.Status(xfer(bus, bytes([mlx.CMD_RM | mlx.ZYXT_XYZ]), 7)[0]).error


def test_rm_of_items_the_conversion_did_not_make_is_refused(bus):
    configure_raw(bus)
    status(bus, bytes([mlx.CMD_SM | mlx.ZYXT_X]))
    bus.sleep(0.01)
    assert mlx.Status(xfer(bus, bytes([mlx.CMD_RM | mlx.ZYXT_XYZ]), 7)[0]).error
    reply = xfer(bus, bytes([mlx.CMD_RM | mlx.ZYXT_X]), 3)
    assert not mlx.Status(reply[0]).error and mlx.Status(reply[0]).d == 0


def test_zyxt_zero_uses_burst_sel(bus):
    configure_raw(bus, mlx.Settings(burst_sel=mlx.ZYXT_XYZT))
    assert status(bus, bytes([mlx.CMD_SM])).sm_mode
    bus.sleep(0.01)
    reply = xfer(bus, bytes([mlx.CMD_RM]), 9)
    assert mlx.Status(reply[0]).d == 3  # four words: T, X, Y, Z


def test_measurement_refused_with_nothing_selected_or_forbidden_settings(bus):
    configure_raw(bus, mlx.Settings(burst_sel=0))
    assert status(bus, bytes([mlx.CMD_SM])).error  # zyxt 0 and BURST_SEL 0
    drv = MLX90393(bus, ADDR, sleep=bus.sleep)
    drv.reset()  # power-on CONF3 is OSR 0, DIG_FILT 0: forbidden
    s = status(bus, bytes([mlx.CMD_SM | mlx.ZYXT_XYZ]))
    assert s.error and not s.sm_mode


@pytest.mark.parametrize(
    ("first", "second"),
    [
        (mlx.CMD_SM, mlx.CMD_SM),
        (mlx.CMD_SM, mlx.CMD_SB),
        (mlx.CMD_SB, mlx.CMD_SM),
        (mlx.CMD_SB, mlx.CMD_SB),
        (mlx.CMD_SB, mlx.CMD_SW),
        (mlx.CMD_SW, mlx.CMD_SB),
    ],
)
def test_a_mode_command_while_another_mode_is_active_is_refused(bus, first, second):
    configure_raw(bus)
    bit = {mlx.CMD_SM: mlx.STATUS_SM_MODE, mlx.CMD_SB: mlx.STATUS_BURST_MODE, mlx.CMD_SW: mlx.STATUS_WOC_MODE}
    assert status(bus, bytes([first | mlx.ZYXT_XYZ])).byte & bit[first]
    s = status(bus, bytes([second | mlx.ZYXT_XYZ]))
    assert s.error
    if second != first:
        assert not s.byte & bit[second]  # the refused mode's bit stays clear
    assert status(bus, bytes([mlx.CMD_EX])).byte & 0xE0 == 0  # EX leaves every mode


# --- burst -------------------------------------------------------------------------
def test_burst_mode_refuses_registers_and_delivers_each_result_once(bus):
    settings = mlx.Settings()
    configure_raw(bus, settings)
    assert status(bus, bytes([mlx.CMD_SB | mlx.ZYXT_XYZ])).burst_mode
    assert status(bus, bytes([mlx.CMD_RR, 0x00])).error
    assert status(bus, bytes([mlx.CMD_WR, 0, 0, 0x00])).error
    assert status(bus, bytes([mlx.CMD_HR])).error
    bus.sleep(settings.single_measurement_us() * 1e-6 * mlx.OSCILLATOR_SLOWEST)
    first = xfer(bus, bytes([mlx.CMD_RM | mlx.ZYXT_XYZ]), 7)
    assert not mlx.Status(first[0]).error and mlx.Status(first[0]).burst_mode
    assert mlx.Status(xfer(bus, bytes([mlx.CMD_RM | mlx.ZYXT_XYZ]), 7)[0]).error  # not yet
    bus.sleep(settings.burst_interval_us() * 1e-6 * mlx.OSCILLATOR_SLOWEST)
    assert not mlx.Status(xfer(bus, bytes([mlx.CMD_RM | mlx.ZYXT_XYZ]), 7)[0]).error


def test_burst_results_follow_a_changing_field(bus, scene):
    drv = MLX90393(bus, ADDR, sleep=bus.sleep)
    drv.reset()
    drv.configure(mlx.Settings())
    drv.start_burst(mlx.ZYXT_XYZ)
    bus.sleep(0.01)
    before = drv.read_measurement().field_t
    scene.set_field(ADDR, [0.0, 0.0, -3e-3])
    bus.sleep(0.01)
    after = drv.read_measurement().field_t
    assert before[2] == pytest.approx(1500e-6, abs=10e-6)
    assert after[2] == pytest.approx(-3e-3, abs=10e-6)


# --- what the conversion produces --------------------------------------------------------
@pytest.mark.parametrize(
    "settings",
    [
        mlx.Settings(),
        mlx.Settings(gain_sel=7, res_x=0, res_y=1, res_z=2),
        mlx.Settings(gain_sel=4, res_x=1, res_y=1, res_z=1, tcmp_en=True),
    ],
)
def test_noiseless_readings_are_the_field_quantised_to_the_lsb(bus, scene, settings):
    drv = MLX90393(bus, ADDR, sleep=bus.sleep)
    drv.reset()
    drv.configure(settings)
    m = drv.measure(mlx.ZYXT_XYZT)
    for i, axis in enumerate("xyz"):
        lsb = settings.sensitivity_ut(axis) * 1e-6
        assert m.field_t[i] == pytest.approx(round(scene.fields_t[ADDR][i] / lsb) * lsb, abs=1e-12)
    assert m.temperature_c == pytest.approx(31.5, abs=0.5 / 45.2)
    assert not m.any_saturated


@pytest.mark.parametrize("when_s", [SM_XYZ_S / 2, 2 * SM_XYZ_S])  # mid-conversion, and done before the RM
def test_a_conversion_keeps_the_settings_it_started_with(bus, scene, when_s):
    """The words an RM returns were made by the conversion: a WR of GAIN_SEL after its SM
    does not rescale them (until 2026-11-27 the emulator coded them at RM time with the
    registers then, so a driver that changed the gain and decoded with the new one read
    the right field here and a wrong one, 5x off, on a chip)."""
    started, changed = (
        mlx.Settings(gain_sel=7, res_x=0, res_y=0, res_z=0),
        mlx.Settings(gain_sel=0, res_x=0, res_y=0, res_z=0),
    )
    configure_raw(bus, started)
    assert not status(bus, bytes([mlx.CMD_SM | mlx.ZYXT_XYZ])).error
    bus.sleep(when_s)
    conf1 = changed.to_registers()[mlx.REG_CONF1]
    wr = status(bus, bytes([mlx.CMD_WR, conf1 >> 8, conf1 & 0xFF, mlx.REG_CONF1 << 2]))
    assert wr.error == (when_s < SM_XYZ_S)  # refused while the conversion is under way (the strict choice)
    bus.sleep(2 * SM_XYZ_S)
    reply = xfer(bus, bytes([mlx.CMD_RM | mlx.ZYXT_XYZ]), 7)
    assert not mlx.Status(reply[0]).error
    x = mlx.raw_to_counts((reply[1] << 8) | reply[2], started.raw_format("x"))
    assert x == round(
        scene.fields_t[ADDR][0] * 1e6 / started.sensitivity_ut("x")
    )  # 667 counts at GAIN_SEL 7, not 133
    # the next conversion takes the new gain (written again once idle, where it was refused)
    assert not status(bus, bytes([mlx.CMD_WR, conf1 >> 8, conf1 & 0xFF, mlx.REG_CONF1 << 2])).error
    assert rm_counts(bus, changed)[0] == round(scene.fields_t[ADDR][0] * 1e6 / changed.sensitivity_ut("x"))


TCMP = mlx.Settings(gain_sel=4, res_x=1, res_y=1, res_z=1, tcmp_en=True)


def rm_counts(bus, settings: mlx.Settings) -> list[int]:
    """SM and RM of X, Y, Z (status read), decoded as counts from zero field."""
    assert not status(bus, bytes([mlx.CMD_SM | mlx.ZYXT_XYZ])).error
    bus.sleep(settings.single_measurement_us() * 1.2e-6)
    reply = xfer(bus, bytes([mlx.CMD_RM | mlx.ZYXT_XYZ]), 7)
    assert not mlx.Status(reply[0]).error
    return [
        mlx.raw_to_counts((reply[1 + 2 * i] << 8) | reply[2 + 2 * i], settings.raw_format(a))
        for i, a in enumerate("xyz")
    ]


def test_with_tcmp_the_output_is_referenced_to_the_offset_registers(bus, scene):
    """TCMP_EN's output reads OFFSET_X/Y/Z at zero field: at 0x8000 the field, at the
    power-on 0 garbage (wrapped to the far side of the span, with the wrong sign)."""
    configure_raw(bus, TCMP)
    truth = [round(scene.fields_t[ADDR][i] * 1e6 / TCMP.sensitivity_ut(a)) for i, a in enumerate("xyz")]
    at_zero = rm_counts(bus, TCMP)
    assert all(abs(c - t) > 30000 for c, t in zip(at_zero, truth))  # nowhere near: garbage
    for reg, value in zip(mlx.REG_OFFSETS, (mlx.OFFSET_TCMP_ZERO, mlx.OFFSET_TCMP_ZERO + 100, 0x8000 - 7)):
        assert not status(bus, bytes([mlx.CMD_WR, value >> 8, value & 0xFF, reg << 2])).error
    assert rm_counts(bus, TCMP) == [truth[0], truth[1] + 100, truth[2] - 7]


def test_without_tcmp_the_offset_registers_change_nothing(bus, scene):
    configure_raw(bus)
    before = rm_counts(bus, mlx.Settings())
    assert not status(bus, bytes([mlx.CMD_WR, 0x12, 0x34, mlx.REG_OFFSET_X << 2])).error
    assert rm_counts(bus, mlx.Settings()) == before


def test_the_driver_sets_the_offsets_when_it_turns_tcmp_on_and_reads_them_back(chip, bus, scene):
    emulated = bus.chips[ADDR]
    assert [emulated.registers[r] for r in mlx.REG_OFFSETS] == [0, 0, 0]  # the paper's settings: no TCMP
    chip.configure(TCMP)
    assert [emulated.registers[r] for r in mlx.REG_OFFSETS] == [mlx.OFFSET_TCMP_ZERO] * 3
    m = chip.measure()
    for i, axis in enumerate("xyz"):
        lsb = TCMP.sensitivity_ut(axis) * 1e-6
        assert m.field_t[i] == pytest.approx(round(scene.fields_t[ADDR][i] / lsb) * lsb, abs=1e-12)
    assert chip.configuration_matches()
    emulated.drift_register(mlx.REG_OFFSET_Y, 0)  # an offset lost: the read-back sees it
    assert not chip.configuration_matches()


def test_readings_past_the_span_or_the_element_limit_are_flagged(bus, scene):
    drv = MLX90393(bus, ADDR, sleep=bus.sleep)
    drv.reset()
    drv.configure(mlx.Settings(gain_sel=7, res_x=0, res_y=0, res_z=0))  # +-4.9 mT span on X/Y
    scene.set_field(ADDR, [6e-3, -1e-3, 80e-3])
    m = drv.measure()
    assert list(m.saturated) == [True, False, True]
    drv.configure(mlx.Settings())  # GAIN_SEL 0, RES 3: +-66 mT span, but the element clips at 50 mT
    m = drv.measure()
    assert list(m.saturated) == [False, False, True]
    assert m.field_t[2] == pytest.approx(50e-3, abs=10e-6)


def test_noise_shrinks_with_conversion_time_as_the_model_says():
    noise = NoiseModel()
    scene = StaticScene({ADDR: np.array([0.0, 0.0, 0.0])})
    stds = {}
    for osr, dig_filt in ((2, 0), (3, 7)):  # TCONVM 835 us and 66 627 us
        # GAIN_SEL 7, RES 0: the LSB (0.15 uT) is small against the noise.
        settings = mlx.Settings(gain_sel=7, res_x=0, res_y=0, res_z=0, osr=osr, dig_filt=dig_filt)
        bus = simulated_bus(scene, clock=VirtualClock(), noise=noise, seed=1)
        drv = MLX90393(bus, ADDR, sleep=bus.sleep)
        drv.reset()
        drv.configure(settings)
        samples = np.array([drv.measure().field_t for _ in range(400)]) * 1e6
        stds[(osr, dig_filt)] = samples.std(axis=0)
        expected_x = noise.sigma_ut("x", settings.tconvm_us())
        # 400 samples: the sample std is within +-15 % of sigma at > 4 standard errors.
        assert stds[(osr, dig_filt)][0] == pytest.approx(expected_x, rel=0.15)
        assert stds[(osr, dig_filt)][2] == pytest.approx(noise.z_factor * expected_x, rel=0.15)
    ratio = stds[(2, 0)][0] / stds[(3, 7)][0]
    assert ratio == pytest.approx(np.sqrt(mlx.tconvm_us(3, 7) / mlx.tconvm_us(2, 0)), rel=0.25)


# --- fault hooks on the chip ---------------------------------------------------------------
def test_stuck_chip_returns_the_same_data_forever(chip, bus, scene):
    first = chip.measure()
    bus.chips[ADDR].stuck = True
    stuck = chip.measure()
    scene.set_field(ADDR, [1e-3, 1e-3, 1e-3])
    for _ in range(3):
        again = chip.measure()
        assert np.array_equal(again.field_t, stuck.field_t)
        assert np.array_equal(again.field_t, first.field_t)
    bus.chips[ADDR].stuck = False
    assert chip.measure().field_t[0] == pytest.approx(1e-3, abs=10e-6)


def test_a_register_that_changes_by_itself_is_caught_by_read_back(chip, bus):
    assert chip.configuration_matches()
    bus.chips[ADDR].drift_register(mlx.REG_CONF3, 0x0000, at=bus.monotonic() + 1.0)
    assert chip.configuration_matches()
    bus.sleep(1.0)
    assert not chip.configuration_matches()
    chip.configure(chip.settings)
    assert chip.configuration_matches()


def test_driver_refusals_carry_the_status(chip):
    with pytest.raises(ChipRefusedError) as exc:
        chip.read_measurement()  # nothing converted yet
    assert exc.value.status.error and exc.value.address == ADDR
    chip.start_burst()
    with pytest.raises(ChipRefusedError, match="RR 0x00 refused"):
        chip.read_register(0)
    with pytest.raises(ChipRefusedError, match="SM refused"):
        chip.start_single()


def test_driver_reports_a_nack_with_the_kernel_errno(chip, bus):
    bus.faults.nack(ADDR)
    with pytest.raises(ChipNotRespondingError) as exc:
        chip.exit_mode()
    assert exc.value.errno == errno.EREMOTEIO and isinstance(exc.value, OSError)
