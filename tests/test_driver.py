"""Driver checks that a well-behaved emulator never triggers: a scripted bus
answers with the bytes a broken or confused chip could send."""

from __future__ import annotations

import ctypes

import numpy as np
import pytest

from ftsensord.chip import mlx90393 as mlx
from ftsensord.chip.driver import MLX90393
from ftsensord.errors import (
    ChipProtocolError,
    ChipRefusedError,
    ForbiddenSettingError,
    RegisterVerifyError,
)

from .conftest import ADDR


class ScriptedBus:
    """Answers each command from ``replies`` (keyed by the first command byte)."""

    def __init__(self, replies: dict[int, bytes]):
        self.replies = replies
        self.sent: list[bytes] = []

    def i2c_rdwr(self, write, read) -> None:
        command = bytes(write)
        self.sent.append(command)
        reply = self.replies[command[0]]
        ctypes.memmove(read.buf, reply + b"\xff" * read.len, read.len)


def configured(bus) -> MLX90393:
    drv = MLX90393(bus, ADDR, sleep=lambda s: None)
    drv.settings = mlx.Settings()
    return drv


def test_rm_reply_whose_d_bits_disagree_with_the_request_is_refused():
    # Asked for X, Y, Z (6 bytes) but D1:D0 = 0 says 2 bytes follow.
    drv = configured(ScriptedBus({0x4E: bytes([0x00, 0x40, 0x00, 0x40, 0x00, 0x40, 0x00])}))
    with pytest.raises(ChipProtocolError, match="expects 6 data bytes, status D1:D0 says 2"):
        drv.read_measurement(mlx.ZYXT_XYZ)


def test_rr_reply_with_wrong_d_bits_is_refused():
    drv = configured(ScriptedBus({0x50: bytes([0x02, 0x00, 0x7C])}))
    with pytest.raises(ChipProtocolError, match="RR expects 2 data bytes"):
        drv.read_register(0)


def test_error_bit_raises_refused_with_the_decoded_status():
    drv = configured(ScriptedBus({0x3E: bytes([0x10])}))
    with pytest.raises(ChipRefusedError) as exc:
        drv.start_single()
    assert exc.value.status == mlx.Status(0x10)


def test_mode_command_accepted_without_its_mode_bit_is_a_protocol_error():
    drv = configured(ScriptedBus({0x1E: bytes([0x00])}))
    with pytest.raises(ChipProtocolError, match="without its mode bit"):
        drv.start_burst()


def test_rt_reply_without_rs_is_a_protocol_error():
    drv = configured(ScriptedBus({0x80: b"\x00", 0xF0: b"\x00"}))
    with pytest.raises(ChipProtocolError, match="lacks RS"):
        drv.reset()


def test_a_register_that_does_not_hold_its_value_fails_verification():
    drv = configured(ScriptedBus({0x60: b"\x00", 0x50: b"\x00\x00\x00"}))
    with pytest.raises(RegisterVerifyError, match="reads 0x0000 after writing 0x1234"):
        drv.write_register(0x04, 0x1234)


def test_forbidden_settings_are_refused_before_any_byte_is_sent():
    bus = ScriptedBus({})
    drv = MLX90393(bus, ADDR)
    with pytest.raises(ForbiddenSettingError):
        drv.configure(mlx.Settings(osr=0, dig_filt=0))
    assert bus.sent == []


def test_driver_refuses_bad_arguments_locally():
    drv = configured(ScriptedBus({}))
    with pytest.raises(ValueError):
        drv.read_register(0x40)
    with pytest.raises(ValueError, match="not writable"):
        drv.write_register(mlx.REG_TREF, 0)
    with pytest.raises(ValueError):
        MLX90393(ScriptedBus({}), 0x48)


def test_decoding_before_configure_is_refused():
    drv = MLX90393(ScriptedBus({}), ADDR)
    with pytest.raises(ChipProtocolError, match="before configure"):
        drv.decode_measurement(b"\x02" + b"\x40\x00" * 3)


def test_decode_uses_each_axis_resolution_and_the_chips_tref():
    drv = configured(ScriptedBus({}))
    drv.settings = mlx.Settings(gain_sel=7, res_x=0, res_y=2, res_z=3)
    drv.tref = 46000
    reply = (
        bytes([0x03])
        + (46000 + 452).to_bytes(2, "big")
        + (0xFFFF).to_bytes(2, "big")
        + (32768 + 100).to_bytes(2, "big")
        + (16384 - 11000).to_bytes(2, "big")
    )
    m = drv.decode_measurement(reply, mlx.ZYXT_XYZT)
    assert m.temperature_c == pytest.approx(45.0)
    assert m.field_t[0] == pytest.approx(-1 * mlx.sensitivity_ut(7, 0, "x") * 1e-6)
    assert m.field_t[1] == pytest.approx(100 * mlx.sensitivity_ut(7, 2, "y") * 1e-6)
    assert list(m.saturated) == [False, False, True]
    assert m.raw["t"] == 46452


def test_partial_reads_leave_unread_axes_nan():
    drv = configured(ScriptedBus({}))
    m = drv.decode_measurement(bytes([0x00, 0x40, 0x10]), mlx.ZYXT_Y)
    assert np.isnan(m.field_t[0]) and np.isnan(m.field_t[2]) and not np.isnan(m.field_t[1])
    assert m.temperature_c is None


def test_the_read_back_compares_with_the_settings_written_last(chip, bus):
    """Configured again with other settings, a chip whose registers went back to the first
    settings' words does not match: what is expected follows the settings, not the words."""
    first = {r: bus.chips[ADDR].registers[r] for r in (mlx.REG_CONF1, mlx.REG_CONF2, mlx.REG_CONF3)}
    assert chip.configuration_matches()
    chip.configure(mlx.Settings(gain_sel=5))
    assert chip.configuration_matches()
    for r, v in first.items():
        bus.chips[ADDR].registers[r] = v  # the words of the first settings, by themselves
    assert not chip.configuration_matches()
    chip.configure(mlx.Settings())  # the first settings again: the same words now match
    assert chip.configuration_matches()
