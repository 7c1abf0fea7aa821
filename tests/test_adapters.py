"""The real bus: Linux adapters' rules, the chip's real status bytes, the board's costs,
the bus lock, and `ftsensord doctor`."""

from __future__ import annotations

import errno
import json
import os

import pytest
import smbus2.smbus2 as smbus2_module
from smbus2 import i2c_msg

from ftsensord.acquire.board import (
    BoardReport,
    Measured,
    SysfsAdapter,
    bus_timing,
    know_board,
)
from ftsensord.acquire.bound import cycle_bound
from ftsensord.acquire.bus import BusBusyError, LinuxI2CBus, open_bus, parse_bus
from ftsensord.acquire.doctor import doctor
from ftsensord.acquire.reader import Reader, probe_shapes
from ftsensord.chip import mlx90393 as mlx
from ftsensord.chip.driver import MLX90393
from ftsensord.chip.i2c import ADAPTER_RULES
from ftsensord.cli import main
from ftsensord.errors import ChipNotRespondingError, ChipProtocolError, ConfigError
from ftsensord.sim import NOISELESS, VirtualClock, simulated_bus, two_sensor_scene

from .conftest import ADDR

OTHER = 0x14
ALL = range(0x0C, 0x1C)


def sim(scene, adapter: str, **kw):
    return simulated_bus(scene, clock=VirtualClock(), noise=NOISELESS, bus_hz=400e3, adapter=adapter, **kw)


def wr(address: int, value: int) -> i2c_msg:
    return i2c_msg.write(address, [mlx.CMD_WR, value >> 8, value & 0xFF, 0x04 << 2])


# --- each adapter's rules ------------------------------------------------------------------
def test_bcm2835_refuses_a_read_that_is_not_last_before_touching_any_chip(scene):
    bus = sim(scene, "bcm2835", ioctl_s=80e-6)
    first_read = i2c_msg.read(ADDR, 1)
    with pytest.raises(OSError) as exc:
        bus.i2c_rdwr(wr(ADDR, 0x42), first_read, wr(OTHER, 0x43), i2c_msg.read(OTHER, 1))
    assert exc.value.errno == errno.EOPNOTSUPP and "only one read message supported, has to be last" in str(
        exc.value
    )
    assert (
        bus.chips[ADDR].registers[0x04] == 0 and bus.chips[OTHER].registers[0x04] == 0
    )  # nothing reached a chip
    assert bytes(first_read) == b"\x00" and bus.refused == 1
    assert bus.clock.now() == pytest.approx(80e-6)  # the ioctl's cost, no wire time


def test_bcm2835_takes_writes_to_many_chips_then_one_read(scene):
    bus = sim(scene, "bcm2835")
    last = i2c_msg.read(OTHER, 1)
    bus.i2c_rdwr(wr(ADDR, 0x42), wr(OTHER, 0x43), last)
    assert bus.chips[ADDR].registers[0x04] == 0x42 and bus.chips[OTHER].registers[0x04] == 0x43
    assert not mlx.Status(bytes(last)[0]).error and bus.refused == 0


def test_designware_refuses_a_second_address_with_einval_and_fills_no_buffer(scene):
    """i2c_dw_xfer_msg() finds the new address while pumping messages into its FIFO:
    what was queued before it reaches the wire, nothing after it; i2c-dev copies no buffer."""
    bus = sim(scene, "designware")
    read = i2c_msg.read(ADDR, 1)
    with pytest.raises(OSError) as exc:
        bus.i2c_rdwr(wr(ADDR, 0x42), read, wr(OTHER, 0x43), i2c_msg.read(OTHER, 1))
    assert exc.value.errno == errno.EINVAL and "invalid target address" in str(exc.value)
    assert bus.chips[ADDR].registers[0x04] == 0x42 and bus.chips[OTHER].registers[0x04] == 0
    assert bytes(read) == b"\x00"
    # One address, reads anywhere: taken.
    bus.i2c_rdwr(wr(OTHER, 0x44), i2c_msg.read(OTHER, 1), wr(OTHER, 0x45), i2c_msg.read(OTHER, 1))
    assert bus.chips[OTHER].registers[0x04] == 0x45


def test_designware_refuses_a_zero_length_message_as_its_quirk_says(scene):
    bus = sim(scene, "designware")
    with pytest.raises(OSError) as exc:
        bus.i2c_rdwr(i2c_msg.write(ADDR, []))
    assert exc.value.errno == errno.EOPNOTSUPP
    sim(scene, "bcm2835").i2c_rdwr(i2c_msg.write(ADDR, []))  # a quick-write probe elsewhere


@pytest.mark.parametrize(
    ("adapter", "err"),
    [("permissive", errno.ENXIO), ("bcm2835", errno.EREMOTEIO), ("designware", errno.EREMOTEIO)],
)
def test_each_adapter_reports_a_nack_with_its_drivers_errno(scene, adapter, err):
    with pytest.raises(OSError) as exc:
        sim(scene, adapter).i2c_rdwr(i2c_msg.write(0x1B, [mlx.CMD_EX]), i2c_msg.read(0x1B, 1))
    assert exc.value.errno == err
    assert ADAPTER_RULES[adapter].nack_errno == err


# --- bus strings -----------------------------------------------------------------------------
def test_bus_strings_carry_the_board():
    spec = parse_bus("sim?adapter=designware&ioctl_us=80&clock_hz=250000")
    assert (spec.kind, spec.arg) == ("sim", None)
    assert spec.timing.adapter == "designware" and spec.timing.ioctl_s == pytest.approx(80e-6)
    assert spec.timing.clock_hz == 250e3
    assert parse_bus("sim:scene.toml?adapter=permissive").arg == "scene.toml"
    default = parse_bus("sim").timing
    assert (
        default.adapter == "bcm2835" and default.ioctl_s == pytest.approx(60e-6) and default.clock_hz is None
    )
    bus = open_bus("sim?adapter=permissive&ioctl_us=0&clock_hz=100000", clock=VirtualClock(), bus_hz=400e3)
    assert (bus.adapter, bus.ioctl_s, bus.wire_hz) == ("permissive", 0.0, 100e3)


@pytest.mark.parametrize(
    ("spec", "named"),
    [
        ("sim?adapter=smbus", "permissive or bcm2835 or designware"),
        ("sim?speed=1", "unknown option 'speed'"),
        ("sim?ioctl_us=-1", "ioctl_us"),
        ("sim?ioctl_us=fast", "ioctl_us"),
        ("sim?clock_hz=nan", "clock_hz"),
        ("sim?clock_hz=5e6", "clock_hz"),
        ("sim?adapter", "adapter"),
        ("sim?adapter=bcm2835&adapter=permissive", "adapter"),
        ("i2c:1?adapter=bcm2835", "simulated bus only"),
    ],
)
def test_a_bad_option_is_refused_naming_it_and_what_is_accepted(spec, named):
    with pytest.raises(ConfigError) as exc:
        parse_bus(spec)
    assert named in str(exc.value)


# --- the reader on each adapter --------------------------------------------------------------
@pytest.mark.parametrize("adapter", ["permissive", "bcm2835", "designware"])
@pytest.mark.parametrize("scheduler", ["overlapped", "burst"])
def test_the_reader_pays_no_refused_ioctl_after_learning_the_adapter(adapter, scheduler):
    bus = simulated_bus(
        two_sensor_scene(), clock=VirtualClock(), bus_hz=400e3, adapter=adapter, ioctl_s=80e-6
    )
    reader = Reader(bus, [MLX90393(bus, a, sleep=bus.sleep) for a in ALL], scheduler, mlx.Settings())
    assert reader.start() == {}
    learnt = bus.refused
    assert learnt <= 1  # the probe, once
    expected = {"permissive": (True, True), "bcm2835": (False, True), "designware": (True, False)}[adapter]
    assert (reader.shapes.reads_inside, reader.shapes.many_addresses) == expected
    bound = cycle_bound(scheduler, 16, mlx.Settings(), 400e3, 80e-6, adapter=adapter)
    for _ in range(30):
        t0, n0 = bus.monotonic(), bus.transfers
        results = reader.read()
        assert bus.transfers - n0 <= bound.ioctls
        bus.clock.wait_until(t0 + 0.01)
    assert bus.refused == learnt and sum(r.ok for r in results.values()) >= 15


def test_a_refusal_makes_the_reader_learn_again_and_then_refuse_no_more():
    """An adapter that takes less than was learnt (here: the rules change under it)
    costs one refused ioctl and one probe, then none."""
    bus = simulated_bus(two_sensor_scene(), clock=VirtualClock(), bus_hz=400e3, adapter="permissive")
    reader = Reader(bus, [MLX90393(bus, a, sleep=bus.sleep) for a in ALL], "overlapped", mlx.Settings())
    reader.start()
    bus.rules = ADAPTER_RULES["bcm2835"]
    for _ in range(3):
        reader.read()
        bus.clock.sleep(0.01)
    refused = bus.refused
    assert 1 <= refused <= 3 and not reader.shapes.reads_inside and reader.shapes.many_addresses
    for _ in range(20):
        assert all(r.ok for r in reader.read().values())
        bus.clock.sleep(0.01)
    assert bus.refused == refused


def test_the_probe_says_nothing_when_no_chip_answers(scene):
    bus = sim(scene, "bcm2835")
    assert probe_shapes(bus, [MLX90393(bus, a) for a in (0x0D, 0x0E)]) is None
    assert bus.refused == 0


# --- the chip answers like a real one --------------------------------------------------------
CAPTURED = {  # logic captures of real chips (docs/design/simulator.md)
    "EX": {0x01, 0x02},
    "WR": {0x01, 0x02},
    "RT": {0x05, 0x06},
    "SM": {0x21, 0x22},
    "SB": {0x81, 0x82},
}


def raw(bus, address: int, command: bytes, n: int = 1) -> int:
    w, r = i2c_msg.write(address, command), i2c_msg.read(address, n)
    bus.i2c_rdwr(w, r)
    return bytes(r)[0]


def test_replies_without_data_carry_d1_d0_as_captured_and_vary(scene):
    bus = sim(scene, "bcm2835")
    seen: dict[str, set[int]] = {k: set() for k in CAPTURED}
    drv = MLX90393(bus, ADDR, sleep=bus.sleep)
    for _ in range(40):
        seen["EX"].add(raw(bus, ADDR, bytes([mlx.CMD_EX])))
        seen["RT"].add(raw(bus, ADDR, bytes([mlx.CMD_RT])))
        bus.sleep(2e-3)
        value = mlx.Settings().to_registers()[mlx.REG_CONF3]
        seen["WR"].add(raw(bus, ADDR, bytes([mlx.CMD_WR, value >> 8, value & 0xFF, mlx.REG_CONF3 << 2])))
        seen["SM"].add(raw(bus, ADDR, bytes([mlx.CMD_SM | mlx.ZYXT_XYZ])))
        bus.sleep(5e-3)
        drv.settings = mlx.Settings()
        drv.read_measurement()  # RM's D1:D0 still says its six bytes
        seen["SB"].add(raw(bus, ADDR, bytes([mlx.CMD_SB | mlx.ZYXT_XYZ])))
    assert seen == CAPTURED  # every captured value, and nothing else


def test_a_bare_read_is_not_acknowledged(scene):
    """i2cdetect -r does not find a real chip: a read with no command before it is NACKed,
    with the adapter's errno; a reply is read once."""
    bus = sim(scene, "bcm2835")
    with pytest.raises(OSError) as exc:
        bus.i2c_rdwr(i2c_msg.read(ADDR, 1))
    assert exc.value.errno == errno.EREMOTEIO
    bus.i2c_rdwr(i2c_msg.write(ADDR, [mlx.CMD_EX]))
    bus.i2c_rdwr(i2c_msg.read(ADDR, 1))  # write, stop, then a read of its reply: taken
    with pytest.raises(OSError):
        bus.i2c_rdwr(i2c_msg.read(ADDR, 1))


class WholeByteDriver(MLX90393):
    """A driver that expects the datasheet's idealised status bytes (EX 0x00, SM 0x20)."""

    def exit_mode(self) -> mlx.Status:
        byte = self.transfer(bytes([mlx.CMD_EX]), 1)[0]
        if byte != 0x00:
            raise ChipProtocolError(self.address, f"EX answered 0x{byte:02X}")
        return mlx.Status(byte)


def test_a_driver_comparing_whole_status_bytes_fails_in_simulation(scene):
    bus = sim(scene, "bcm2835")
    with pytest.raises(ChipProtocolError):
        WholeByteDriver(bus, ADDR, sleep=bus.sleep).exit_mode()
    ours = MLX90393(bus, ADDR, sleep=bus.sleep)
    for _ in range(20):  # ours reads D1:D0 only after RR and RM, whatever they hold elsewhere
        ours.reset()
        ours.configure(mlx.Settings())
        assert ours.measure().field_t.shape == (3,)


# --- know the board -------------------------------------------------------------------------
def test_the_measured_clock_and_ioctl_cost_and_the_warning(scene):
    bus = sim(scene, "bcm2835", ioctl_s=80e-6, clock_hz=250e3)
    report = know_board(bus, ADDR, 400e3)
    assert report.measured.clock_hz == pytest.approx(250e3, rel=1e-6)
    assert report.measured.ioctl_s == pytest.approx(80e-6, rel=1e-6)
    (warning,) = report.warnings
    assert (
        "250 kHz" in warning and "400 kHz" in warning and "core_freq" in warning and "force_turbo" in warning
    )
    assert know_board(sim(scene, "bcm2835"), ADDR, 400e3).warnings == []  # the clock it was told


def test_the_sysfs_folder_names_driver_and_kernel_clock(tmp_path):
    folder = tmp_path / "i2c-1"
    (folder / "of_node").mkdir(parents=True)
    (folder / "of_node" / "clock-frequency").write_bytes((100000).to_bytes(4, "big"))
    (tmp_path / "drivers" / "i2c-bcm2835").mkdir(parents=True)
    (folder / "device").mkdir()
    (folder / "device" / "driver").symlink_to(tmp_path / "drivers" / "i2c-bcm2835")
    found = SysfsAdapter.read(1, tmp_path)
    assert (found.driver, found.adapter, found.configured_hz) == ("i2c-bcm2835", "bcm2835", 100e3)
    assert bus_timing("i2c:1", tmp_path).adapter == "bcm2835"
    assert SysfsAdapter.read(2, tmp_path) == SysfsAdapter(2, None, None)
    report = BoardReport(found.driver, found.adapter, found.configured_hz, 400e3, Measured(60e-6, 99e3))
    report.check()
    assert len(report.warnings) == 1 and "dtparam=i2c_arm_baudrate=400000" in report.warnings[0]
    assert "100 kHz" in report.warnings[0]


# --- the bus lock ----------------------------------------------------------------------------
@pytest.fixture
def device(monkeypatch, tmp_path):
    """/dev/i2c-1 is a temporary file (so flock works), the I2C ioctls are faked."""
    path = tmp_path / "i2c-1"
    path.write_bytes(b"")
    real_open = os.open

    def fake_open(p, flags, *args):
        return real_open(str(path) if str(p) == "/dev/i2c-1" else p, flags, *args)

    def fake_ioctl(fd, request, arg):
        if request == 0x0705:  # I2C_FUNCS
            arg.value = 1
            return 0
        raise OSError(errno.EREMOTEIO, "no chip")

    monkeypatch.setattr(smbus2_module.os, "open", fake_open)
    monkeypatch.setattr(smbus2_module, "ioctl", fake_ioctl)
    return path


def test_an_exclusive_bus_is_refused_to_a_second_user_unless_forced(device):
    daemon = open_bus("i2c:1", exclusive=True)
    assert isinstance(daemon, LinuxI2CBus) and daemon.locked
    with pytest.raises(BusBusyError) as exc:
        open_bus("i2c:1", exclusive=True)
    assert "/dev/i2c-1" in str(exc.value) and "--force" in str(exc.value)
    with pytest.raises(BusBusyError):
        doctor("i2c:1")
    forced = open_bus("i2c:1", exclusive=True, force=True)
    assert not forced.locked
    forced.close()
    daemon.close()
    again = open_bus("i2c:1", exclusive=True)  # closing released the lock
    assert again.locked
    again.close()


def test_a_real_bus_without_chips_is_reported_not_crashed(device):
    with pytest.raises(ChipNotRespondingError):
        MLX90393(open_bus("i2c:1"), ADDR).exit_mode()


# --- doctor ----------------------------------------------------------------------------------
def test_doctor_runs_each_scheduler_at_its_bound(capsys):
    assert main(["doctor", "--bus", "sim?adapter=bcm2835&ioctl_us=80", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["adapter"] == "bcm2835" and report["ioctl_us"] == pytest.approx(80, rel=1e-6)
    assert report["clock_hz"] == pytest.approx(400e3, rel=1e-6)
    assert report["accepts"] == {
        "read_not_last": False,
        "several_addresses": True,
        "transfers": report["accepts"]["transfers"],
    }
    assert len(report["chips"]) == 16 and all(c["errors"]["no_answer"] == 0 for c in report["chips"])
    assert set(report["schedulers"]) == {"naive", "overlapped", "burst"}
    for run in report["schedulers"].values():
        assert 0.9 <= run["measured_hz"] / run["bound_hz"] <= 1.02
        assert run["refused_ioctls"] == 0
        # On the virtual clock the host spends no time: a cycle is its transfers, waits and idle.
        t = run["cycle_us"]
        assert t["host"] == pytest.approx(0, abs=1e-3) and t["transfers"] > 0
        assert t["transfers"] + t["waits"] + t["idle"] == pytest.approx(1e6 / run["measured_hz"], rel=1e-9)
