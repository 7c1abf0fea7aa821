"""The real smbus2 code path, with the kernel replaced at the ioctl boundary.

``smbus2.SMBus`` opens ``/dev/i2c-1`` and calls ``ioctl(fd, I2C_RDWR, data)``
with its ctypes ``i2c_rdwr_ioctl_data``; here a fake kernel decodes exactly
those structures (as ``drivers/i2c/i2c-dev.c`` would) and hands the messages
to the emulated chips. So the bytes tested are the ones that would reach
``/dev/i2c-N``.
"""

from __future__ import annotations

import ctypes
import errno
import os

import numpy as np
import pytest
import smbus2.smbus2 as smbus2_module

from ftsensord.acquire.bus import LinuxI2CBus, open_bus
from ftsensord.chip import mlx90393 as mlx
from ftsensord.chip.driver import MLX90393
from ftsensord.errors import ChipNotRespondingError
from ftsensord.sim import NOISELESS, VirtualClock, simulated_bus

from .conftest import ADDR

# From linux/i2c-dev.h and linux/i2c.h, written out so a wrong constant in the
# code under test cannot hide behind the same wrong constant here.
I2C_RDWR = 0x0707
I2C_FUNCS = 0x0705
I2C_M_RD = 0x0001
I2C_FUNC_I2C = 0x00000001
FAKE_FD = 1_000_003


class FakeKernel:
    """Stands in for the i2c-dev driver: records every transfer, forwards it."""

    def __init__(self, sim_bus):
        self.sim_bus = sim_bus
        self.transfers: list[list[tuple[int, int, int, bytes | None]]] = []
        self.opened: list[str] = []
        self.fail_with: int | None = None

    def open(self, path, flags, *args, _real=os.open):
        if isinstance(path, str) and path.startswith("/dev/i2c-"):
            assert flags & os.O_RDWR
            self.opened.append(path)
            return FAKE_FD
        return _real(path, flags, *args)

    def close(self, fd, _real=os.close):
        if fd != FAKE_FD:
            _real(fd)

    def ioctl(self, fd, request, arg):
        assert fd == FAKE_FD
        if request == I2C_FUNCS:
            arg.value = I2C_FUNC_I2C
            return 0
        assert request == I2C_RDWR, f"unexpected ioctl 0x{request:04X}"
        msgs = [arg.msgs[i] for i in range(arg.nmsgs)]
        self.transfers.append(
            [
                (m.addr, m.flags, m.len, None if m.flags & I2C_M_RD else ctypes.string_at(m.buf, m.len))
                for m in msgs
            ]
        )
        if self.fail_with is not None:
            raise OSError(self.fail_with, os.strerror(self.fail_with))
        self.sim_bus.i2c_rdwr(*msgs)
        return 0


@pytest.fixture
def kernel(monkeypatch, scene):
    # The permissive adapter: these tests are about the bytes i2c-dev gets, not a driver's rules.
    sim_bus = simulated_bus(scene, clock=VirtualClock(), noise=NOISELESS, adapter="permissive")
    fake = FakeKernel(sim_bus)
    monkeypatch.setattr(smbus2_module.os, "open", fake.open)
    monkeypatch.setattr(smbus2_module.os, "close", fake.close)
    monkeypatch.setattr(smbus2_module, "ioctl", fake.ioctl)
    return fake


def test_driver_over_real_smbus2_sends_the_expected_kernel_messages(kernel, scene):
    bus = open_bus("i2c:1")
    assert isinstance(bus, LinuxI2CBus) and kernel.opened == ["/dev/i2c-1"]
    drv = MLX90393(bus, ADDR, sleep=kernel.sim_bus.sleep)
    kernel.transfers.clear()

    drv.exit_mode()
    assert kernel.transfers[-1] == [(ADDR, 0, 1, b"\x80"), (ADDR, I2C_M_RD, 1, None)]

    drv.write_register(mlx.REG_CONF3, 0x1234 & 0x1FFF)
    assert kernel.transfers[-2] == [(ADDR, 0, 4, bytes([0x60, 0x12, 0x34, 0x08])), (ADDR, I2C_M_RD, 1, None)]
    assert kernel.transfers[-1] == [(ADDR, 0, 2, bytes([0x50, 0x08])), (ADDR, I2C_M_RD, 3, None)]

    drv.configure(mlx.Settings())
    drv.start_single(mlx.ZYXT_XYZ)
    assert kernel.transfers[-1] == [(ADDR, 0, 1, b"\x3e"), (ADDR, I2C_M_RD, 1, None)]
    kernel.sim_bus.sleep(0.005)
    m = drv.read_measurement(mlx.ZYXT_XYZ)
    assert kernel.transfers[-1] == [(ADDR, 0, 1, b"\x4e"), (ADDR, I2C_M_RD, 7, None)]

    # The data came back through smbus2's ctypes buffers, decoded to tesla.
    lsb = np.array([mlx.Settings().sensitivity_ut(a) for a in "xyz"]) * 1e-6
    assert np.allclose(m.field_t, np.round(scene.fields_t[ADDR] / lsb) * lsb, atol=1e-12)
    bus.close()


def test_a_multi_chip_transfer_goes_out_as_one_ioctl(kernel):
    bus = open_bus("i2c:1")
    chips = [MLX90393(bus, a, sleep=kernel.sim_bus.sleep) for a in (0x0C, 0x14)]
    msgs = [m for c in chips for m in c.messages(bytes([mlx.CMD_EX]), 1)]
    kernel.transfers.clear()
    bus.i2c_rdwr(*msgs)
    assert [(a, f) for a, f, _, _ in kernel.transfers[0]] == [(0x0C, 0), (0x0C, 1), (0x14, 0), (0x14, 1)]
    assert all(not mlx.Status(bytes(m)[0]).error for m in msgs[1::2])


@pytest.mark.parametrize("err", [errno.ENXIO, errno.EREMOTEIO, errno.ETIMEDOUT])
def test_a_kernel_error_becomes_chip_not_responding_with_its_errno(kernel, err):
    bus = open_bus("i2c:1")
    drv = MLX90393(bus, ADDR)
    kernel.fail_with = err
    with pytest.raises(ChipNotRespondingError) as exc:
        drv.exit_mode()
    assert exc.value.errno == err and "EX failed on the bus" in str(exc.value)
