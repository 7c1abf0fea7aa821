"""The simulated bus: the kernel's I2C_RDWR semantics, wire time and fault hooks."""

from __future__ import annotations

import errno

import pytest
from smbus2 import i2c_msg

from ftsensord.chip import mlx90393 as mlx
from ftsensord.chip.driver import MLX90393
from ftsensord.chip.i2c import I2C_RDWR_MAX_MSGS, wire_bits
from ftsensord.errors import ChipNotRespondingError, ChipRefusedError
from ftsensord.sim import (
    NOISELESS,
    MonotonicClock,
    VirtualClock,
    default_scene,
    simulated_bus,
)

from .conftest import ADDR

OTHER = 0x14


def ex_msgs(address: int) -> tuple[i2c_msg, i2c_msg]:
    return i2c_msg.write(address, [mlx.CMD_EX]), i2c_msg.read(address, 1)


@pytest.fixture
def permissive(scene):
    """An adapter that takes any mix of addresses and reads in one ioctl (the kernel's I2C_RDWR)."""
    return simulated_bus(scene, clock=VirtualClock(), noise=NOISELESS, adapter="permissive")


def test_one_transfer_reaches_several_addresses(permissive):
    bus = permissive
    msgs = [*ex_msgs(ADDR), i2c_msg.write(OTHER, [mlx.CMD_RR, mlx.REG_TREF << 2]), i2c_msg.read(OTHER, 3)]
    bus.i2c_rdwr(*msgs)
    assert mlx.Status(bytes(msgs[1])[0]).error is False
    assert bytes(msgs[3]) == b"\x00" + mlx.TREF_TYPICAL.to_bytes(2, "big")
    assert bus.transfers == 1


def test_at_most_42_messages_per_transfer(permissive):
    bus = permissive
    bus.i2c_rdwr(*[m for _ in range(I2C_RDWR_MAX_MSGS // 2) for m in ex_msgs(ADDR)])
    with pytest.raises(OSError) as exc:
        bus.i2c_rdwr(*[m for _ in range(I2C_RDWR_MAX_MSGS // 2 + 1) for m in ex_msgs(ADDR)][:43])
    assert exc.value.errno == errno.EINVAL
    with pytest.raises(OSError):
        bus.i2c_rdwr()


def test_absent_address_aborts_the_transfer_but_earlier_messages_happened(permissive):
    bus = permissive
    sm = i2c_msg.write(ADDR, [mlx.CMD_WR, 0x00, 0x42, 0x04 << 2])
    with pytest.raises(OSError) as exc:
        bus.i2c_rdwr(sm, i2c_msg.read(ADDR, 1), *ex_msgs(0x1B))
    assert exc.value.errno == errno.ENXIO and "0x1B" in str(exc.value)
    assert bus.chips[ADDR].registers[0x04] == 0x42


def test_a_failed_transfer_fills_no_read_buffer_as_i2c_dev(permissive):
    bus = permissive
    read = i2c_msg.read(ADDR, 3)
    with pytest.raises(OSError):
        bus.i2c_rdwr(i2c_msg.write(ADDR, [mlx.CMD_RR, mlx.REG_TREF << 2]), read, *ex_msgs(0x1B))
    assert bytes(read) == b"\x00\x00\x00"


def test_nack_errno_is_configurable_for_adapters_that_say_eremoteio(scene):
    from ftsensord.sim import SimulatedBus
    from ftsensord.sim.chip import EmulatedMLX90393

    bus = SimulatedBus([EmulatedMLX90393(ADDR, scene)], nack_errno=errno.EREMOTEIO)
    with pytest.raises(OSError) as exc:
        bus.i2c_rdwr(*ex_msgs(0x0D))
    assert exc.value.errno == errno.EREMOTEIO


def test_transient_nack_clears_after_its_count(bus):
    bus.faults.nack(ADDR, count=2)
    for _ in range(2):
        with pytest.raises(OSError):
            bus.i2c_rdwr(*ex_msgs(ADDR))
    bus.i2c_rdwr(*ex_msgs(ADDR))
    bus.i2c_rdwr(*ex_msgs(OTHER))  # the other chip was never affected


def test_permanent_nack_lasts_until_cleared(bus):
    bus.faults.nack(ADDR)
    for _ in range(5):
        with pytest.raises(OSError):
            bus.i2c_rdwr(*ex_msgs(ADDR))
    bus.i2c_rdwr(*ex_msgs(OTHER))
    bus.faults.clear()
    bus.i2c_rdwr(*ex_msgs(ADDR))


@pytest.mark.parametrize("err", [errno.EIO, errno.ETIMEDOUT])
def test_bus_wide_io_error_or_timeout(bus, err):
    bus.faults.io_error(count=1, err=err)
    with pytest.raises(OSError) as exc:
        bus.i2c_rdwr(*ex_msgs(OTHER))
    assert exc.value.errno == err
    bus.i2c_rdwr(*ex_msgs(OTHER))


def test_chip_disappears_and_comes_back_at_power_on_defaults(chip, bus):
    gone = bus.detach(ADDR)
    with pytest.raises(ChipNotRespondingError):
        chip.exit_mode()
    gone.power_on()
    bus.attach(gone)
    assert not chip.configuration_matches()  # it lost its configuration
    chip.configure(chip.settings)
    assert chip.measure().field_t[2] == pytest.approx(1500e-6, abs=10e-6)
    with pytest.raises(ValueError):
        bus.attach(gone)


def test_closed_bus_refuses_transfers(bus):
    bus.close()
    with pytest.raises(OSError) as exc:
        bus.i2c_rdwr(*ex_msgs(ADDR))
    assert exc.value.errno == errno.EBADF


# --- wire time -----------------------------------------------------------------------------
def test_wire_bits_match_the_design_notes():
    # SM: write 1 byte, read the status byte: about 100 us at 400 kHz.
    assert wire_bits(ex_msgs(ADDR)) == 39
    # RM of X, Y, Z: write 1 byte, read 7: about 230 us.
    assert wire_bits([i2c_msg.write(ADDR, [0x4E]), i2c_msg.read(ADDR, 7)]) == 93


@pytest.mark.parametrize(("hz", "slowdown"), [(400e3, 1.0), (100e3, 1.0), (400e3, 3.0)])
def test_a_transfer_spends_its_wire_time_on_the_virtual_clock(scene, hz, slowdown):
    clock = VirtualClock()
    bus = simulated_bus(scene, clock=clock, bus_hz=hz, noise=NOISELESS)
    bus.faults.slowdown = slowdown
    msgs = [i2c_msg.write(ADDR, [0x4E]), i2c_msg.read(ADDR, 7)]
    bus.i2c_rdwr(*msgs)
    assert clock.now() == pytest.approx(bus.ioctl_s + 93 * slowdown / hz)  # the ioctl's cost, then the wire


def test_a_nacked_transfer_spends_the_time_up_to_the_nack(scene):
    clock = VirtualClock()
    bus = simulated_bus(scene, clock=clock, bus_hz=400e3)
    with pytest.raises(OSError):
        bus.i2c_rdwr(*ex_msgs(0x1B))
    assert clock.now() == pytest.approx(bus.ioctl_s + 11 / 400e3)  # the ioctl; start, address byte, stop


def test_the_wire_runs_at_the_real_clock_not_the_configured_one(scene):
    """A Pi whose core clock drops under load: 400 kHz configured, 250 kHz on the wire."""
    clock = VirtualClock()
    bus = simulated_bus(scene, clock=clock, bus_hz=400e3, clock_hz=250e3, ioctl_s=80e-6)
    bus.i2c_rdwr(i2c_msg.write(ADDR, [0x4E]), i2c_msg.read(ADDR, 7))
    assert clock.now() == pytest.approx(80e-6 + 93 / 250e3)
    assert bus.timing.clock_hz == 250e3 and bus.timing.ioctl_s == 80e-6 and bus.timing.adapter == "bcm2835"


def test_conversion_sees_the_time_its_command_was_on_the_wire(scene):
    """Wire time counts: SM then RM exactly one conversion later is ready only
    once the RM's own bytes have been clocked out."""
    clock = VirtualClock()
    bus = simulated_bus(scene, clock=clock, bus_hz=100e3, noise=NOISELESS)
    drv = MLX90393(bus, ADDR, sleep=bus.sleep)
    drv.reset()
    drv.configure(mlx.Settings())
    sm_bits, rm_cmd_bits = 19, 19  # the command byte is on the wire 19 bits into a transfer
    conversion = (
        mlx.Settings().single_measurement_us() * 1e-6 * mlx.OSCILLATOR_SLOWEST
    )  # the emulator's default
    for early, accepted in ((1e-6, False), (0.0, True)):
        start = clock.now()
        drv.start_single()
        ready = start + sm_bits / 100e3 + conversion
        clock.wait_until(ready - rm_cmd_bits / 100e3 - early)
        if accepted:
            drv.read_measurement()
        else:
            with pytest.raises(ChipRefusedError):
                drv.read_measurement()
            bus.sleep(0.01)  # let that conversion finish; RM it so the next SM starts afresh
            drv.read_measurement()


def test_real_clock_bus_spends_at_least_its_wire_time():
    # A lower bound only: a busy machine can make it slower, never faster.
    clock = MonotonicClock()
    bus = simulated_bus(default_scene(), clock=clock, bus_hz=100e3)
    t0 = clock.now()
    for _ in range(10):
        bus.i2c_rdwr(i2c_msg.write(ADDR, [0x4E]), i2c_msg.read(ADDR, 7))
    assert clock.now() - t0 >= 10 * 93 / 100e3


def test_real_clock_learns_its_spin_and_never_ends_a_wait_early():
    # The spin is learnt from the sleeps' overshoots; whatever it learns, a wait ends at
    # its time or later (a late end makes the bus slower, never faster, than its wire).
    clock = MonotonicClock()
    for _ in range(2 * MonotonicClock.SPIN_WINDOW):
        t = clock.now() + 300e-6
        clock.wait_until(t)
        assert clock.now() >= t
    assert clock.min_spin_s <= clock._spin <= clock.spin_s


def test_an_smbus2_script_runs_unchanged_on_the_emulator(bus, scene):
    """Public Python MLX90393 examples use smbus2's SMBus calls, not i2c_rdwr (ControlEverything's,
    whose register words and order these are): write_i2c_block_data for WR, write_byte for SM,
    read_byte for a status, read_i2c_block_data for RM. The simulated bus offered only i2c_rdwr,
    so such a script failed with AttributeError before it reached the chip (2026-11-27)."""
    bus.write_i2c_block_data(ADDR, 0x60, [0x00, 0x5C, 0x00])  # WR CONF1: GAIN_SEL 5, HALLCONF 0xC
    assert bus.read_byte(ADDR) & mlx.STATUS_ERROR == 0
    bus.write_i2c_block_data(ADDR, 0x60, [0x02, 0xB4, 0x08])  # WR CONF3: RES 1, DIG_FILT 5, OSR 0
    assert bus.read_byte(ADDR) & mlx.STATUS_ERROR == 0
    bus.write_byte(ADDR, 0x3E)  # SM of X, Y, Z
    assert bus.read_byte(ADDR) & mlx.STATUS_SM_MODE
    bus.sleep(0.5)
    data = bus.read_i2c_block_data(ADDR, 0x4E, 7)  # RM: status and three words
    assert data[0] & mlx.STATUS_ERROR == 0 and len(data) == 7
    x = int.from_bytes(bytes(data[1:3]), "big", signed=True)
    assert x == round(scene.fields_t[ADDR][0] * 1e6 / (0.150 * 5 / 3 * 2))  # GAIN_SEL 5, RES 1: 0.5 uT/LSB
    with pytest.raises(OSError):  # a second read of one reply: the chip does not ACK it
        bus.read_byte(ADDR)
    with pytest.raises(ValueError):  # smbus2's own limit: 32 bytes a block
        bus.read_i2c_block_data(ADDR, 0x4E, 33)
