"""The schedulers against their computed bound, on a virtual clock."""

from __future__ import annotations

import numpy as np
import pytest
from smbus2.smbus2 import I2C_M_RD

from ftsensord.acquire.bound import burst_readback_stays_fresh, cycle_bound
from ftsensord.acquire.health import stuck_cycles_for
from ftsensord.acquire.reader import Reader
from ftsensord.chip import mlx90393 as mlx
from ftsensord.chip.driver import MLX90393
from ftsensord.sim import (
    Fault,
    StaticScene,
    VirtualClock,
    simulated_bus,
    two_sensor_scene,
)


@pytest.mark.parametrize("adapter", ["permissive", "bcm2835", "designware"])
@pytest.mark.parametrize("scheduler", ["naive", "overlapped", "burst"])
@pytest.mark.parametrize("hz", [100e3, 400e3])
def test_a_cycle_takes_exactly_the_computed_bound(scheduler, hz, adapter):
    clock = VirtualClock()
    bus = simulated_bus(two_sensor_scene(), clock=clock, bus_hz=hz, adapter=adapter, ioctl_s=80e-6)
    chips = [MLX90393(bus, a, sleep=bus.sleep) for a in range(0x0C, 0x1C)]
    reader = Reader(bus, chips, scheduler, mlx.Settings(), hz)
    assert reader.start() == {}
    bound = cycle_bound(scheduler, 16, mlx.Settings(), hz, 80e-6, adapter=adapter)
    assert bus.refused == (0 if adapter == "permissive" else 1)  # the probe at start, once
    clock.sleep(0.1)
    for cycle in range(3):
        t0, ioctls = clock.now(), bus.transfers
        results = reader.read()
        reader.upkeep()  # the register read-back, after the samples are out
        took = clock.now() - t0
        assert took == pytest.approx(bound.cycle_s, rel=1e-9)
        assert bus.transfers - ioctls == bound.ioctls and bus.refused == (adapter != "permissive")
        if scheduler == "burst":
            # At the bound no time is left for the burst the read-back restarted (EX, RR,
            # SB): a chip read back one or two cycles ago may have no new data yet, flagged
            # stale (the daemon then reads back every 100 cycles: `burst_readback_stays_fresh`).
            recent = {0x0C + (cycle - k) % 16 for k in (1, 2) if cycle - k >= 0}
            assert all(r.address in recent and r.error.command == "RM" for r in results.values() if not r.ok)
        else:
            assert all(r.ok for r in results.values())
        if scheduler == "burst":  # the chips convert on their own: wait out the cycle
            clock.wait_until(t0 + bound.cycle_s)


@pytest.mark.parametrize("adapter", ["permissive", "bcm2835", "designware"])
@pytest.mark.parametrize("n", [2, 3, 4, 8])
def test_an_overlapped_cycle_of_few_chips_takes_exactly_the_bound(n, adapter):
    """With few chips the chip read back (started last) decides when the RMs go: the reader
    times them from `bound.last_offset_s` as the bound does. Its own copy of that sum left out
    the read's address byte, and cycles of 2-4 chips took 0.4-1.3 % longer than the bound."""
    clock = VirtualClock()
    bus = simulated_bus(two_sensor_scene(), clock=clock, bus_hz=400e3, adapter=adapter, ioctl_s=80e-6)
    reader = Reader(
        bus,
        [MLX90393(bus, a, sleep=bus.sleep) for a in range(0x0C, 0x0C + n)],
        "overlapped",
        mlx.Settings(),
        400e3,
    )
    assert reader.start() == {}
    bound = cycle_bound("overlapped", n, mlx.Settings(), 400e3, 80e-6, adapter=adapter)
    clock.sleep(0.1)
    for _ in range(3):
        t0 = clock.now()
        results = reader.read()
        reader.upkeep()
        assert clock.now() - t0 == pytest.approx(bound.cycle_s, rel=1e-9)  # virtual time: exact but round-off
        assert all(r.ok for r in results.values())


@pytest.mark.parametrize("scheduler", ["naive", "overlapped", "burst"])
def test_with_tcmp_the_read_back_of_the_offsets_is_in_the_bound(scheduler):
    """With TCMP_EN the read-back also reads OFFSET_X/Y/Z (three RRs more), as the bound counts."""
    settings = mlx.Settings(gain_sel=4, res_x=1, res_y=1, res_z=1, tcmp_en=True)
    clock = VirtualClock()
    bus = simulated_bus(two_sensor_scene(), clock=clock, bus_hz=400e3, ioctl_s=80e-6)
    reader = Reader(
        bus, [MLX90393(bus, a, sleep=bus.sleep) for a in range(0x0C, 0x1C)], scheduler, settings, 400e3
    )
    assert reader.start() == {}
    bound = cycle_bound(scheduler, 16, settings, 400e3, 80e-6, adapter=bus.adapter)
    plain = cycle_bound(
        scheduler, 16, mlx.Settings(gain_sel=4, res_x=1, res_y=1, res_z=1), 400e3, 80e-6, adapter=bus.adapter
    )
    assert bound.ioctls == plain.ioctls + 3
    clock.sleep(0.1)
    for _ in range(3):
        t0, ioctls = clock.now(), bus.transfers
        results = reader.read()
        reader.upkeep()
        assert (
            clock.now() - t0 == pytest.approx(bound.cycle_s, rel=1e-9)
            and bus.transfers - ioctls == bound.ioctls
        )
        assert scheduler == "burst" or all(r.ok for r in results.values())
        clock.wait_until(t0 + bound.cycle_s)


@pytest.mark.parametrize("adapter", ["permissive", "bcm2835"])
def test_burst_read_back_after_the_publish_leaves_no_chip_stale(adapter):
    """At 100 Hz (`burst_readback_stays_fresh`) the read-back follows the host's work on
    the samples (here 2 ms of it, a Pi 4's estimate and publish with room to spare) and
    restarts one chip's burst: that chip, read last in the next cycle, has its new result
    by then, and every chip has one in every cycle."""
    clock = VirtualClock()
    bus = simulated_bus(two_sensor_scene(), clock=clock, bus_hz=400e3, adapter=adapter, ioctl_s=80e-6)
    settings = mlx.Settings()
    reader = Reader(bus, [MLX90393(bus, a, sleep=bus.sleep) for a in range(0x0C, 0x1C)], "burst", settings)
    assert reader.start() == {}
    bound = cycle_bound("burst", 16, settings, 400e3, 80e-6, adapter=adapter)
    assert burst_readback_stays_fresh(bound, settings, 100.0)
    clock.sleep(0.1)
    for _ in range(40):  # each chip read back at least twice
        t0 = clock.now()
        results = reader.read()
        assert clock.now() - t0 == pytest.approx(bound.read_s, rel=1e-9)  # the read-back is not in it
        assert all(r.ok for r in results.values()), [hex(r.address) for r in results.values() if not r.ok]
        clock.sleep(2e-3)
        reader.upkeep()
        clock.wait_until(t0 + 0.01)


def _burst_reader(n: int, clock: VirtualClock) -> Reader:
    bus = simulated_bus(two_sensor_scene(), clock=clock, bus_hz=400e3, adapter="bcm2835", ioctl_s=80e-6)
    reader = Reader(
        bus, [MLX90393(bus, a, sleep=bus.sleep) for a in range(0x0C, 0x0C + n)], "burst", mlx.Settings()
    )
    assert reader.start() == {}
    clock.sleep(0.1)
    return reader


def test_burst_reads_back_after_the_rm_when_the_hosts_work_outlasts_the_others_rms():
    """One sensor of 8 chips (the others' RMs: 2.2 ms) and 6 ms of host work a cycle (a slow
    board's estimate): a read-back deferred past it would leave the chip it restarts without
    a new result next cycle, so after the first cycle, which learns the host's work, it
    comes right after the RM (inside `read`), and no chip goes stale."""
    clock = VirtualClock()
    reader = _burst_reader(8, clock)
    bound = cycle_bound("burst", 8, mlx.Settings(), 400e3, 80e-6, adapter="bcm2835")
    for cycle in range(40):
        t0 = clock.now()
        results = reader.read()
        if cycle >= 2:
            assert clock.now() - t0 == pytest.approx(bound.read_s + bound.check_s, rel=1e-9)  # RM, read-back
            assert all(r.ok for r in results.values()), [hex(r.address) for r in results.values() if not r.ok]
        clock.sleep(6e-3)
        reader.upkeep()
        clock.wait_until(t0 + 0.01)


def test_a_reader_without_upkeep_reads_back_after_its_reads():
    """A caller that never calls `upkeep` (the API before it): each read-back comes after
    the next cycle's reads, where it always came, and no chip goes stale (50 Hz, 8 chips)."""
    clock = VirtualClock()
    reader = _burst_reader(8, clock)
    for _ in range(40):
        t0 = clock.now()
        results = reader.read()
        assert all(r.ok for r in results.values()), [hex(r.address) for r in results.values() if not r.ok]
        clock.wait_until(t0 + 0.02)


def test_the_bound_matches_the_design_notes():
    settings = mlx.Settings()
    no_check = {
        s: cycle_bound(s, 16, settings, 400e3, readback=False).rate_hz
        for s in ("naive", "overlapped", "burst")
    }
    assert no_check["naive"] < 20 and 125 < no_check["overlapped"] < 150 and 250 < no_check["burst"] < 290
    assert cycle_bound("overlapped", 16, settings, 100e3).rate_hz < 100  # 16 chips at 100 Hz need 400 kHz


def test_the_temperature_cycle_is_counted_in_the_bound():
    settings = mlx.Settings()
    plain, with_t = (cycle_bound("overlapped", 16, settings, 400e3, temperature=t) for t in (False, True))
    # T adds TCONVT (259 us, +20 %) to the wait and two bytes per chip to the RM transfer.
    assert with_t.cycle_s - plain.cycle_s == pytest.approx(1.2 * 259e-6 + 16 * 18 / 400e3, rel=1e-9)
    # A burst that converts T reads its two bytes per chip in the cycles that ask for it.
    burst, burst_t = (cycle_bound("burst", 16, settings, 400e3, temperature=t) for t in (False, True))
    assert burst_t.read_s - burst.read_s == pytest.approx(16 * 18 / 400e3, rel=1e-9)


@pytest.mark.parametrize("adapter", ["permissive", "bcm2835", "designware"])
def test_a_temperature_cycle_takes_exactly_its_bound(adapter):
    clock = VirtualClock()
    bus = simulated_bus(two_sensor_scene(), clock=clock, bus_hz=400e3, adapter=adapter)
    reader = Reader(
        bus,
        [MLX90393(bus, a, sleep=bus.sleep) for a in range(0x0C, 0x1C)],
        "overlapped",
        mlx.Settings(),
        400e3,
    )
    reader.start()
    clock.sleep(0.1)
    t0 = clock.now()
    results = reader.read(mlx.ZYXT_XYZT)
    assert all(r.ok and r.measurement.temperature_c is not None for r in results.values())
    assert clock.now() - t0 == pytest.approx(
        cycle_bound(
            "overlapped", 16, mlx.Settings(), 400e3, bus.ioctl_s, temperature=True, adapter=adapter
        ).cycle_s,
        rel=1e-9,
    )


@pytest.mark.parametrize("scheduler", ["overlapped", "burst"])
def test_a_reset_goes_one_command_a_cycle_and_no_cycle_overruns(scheduler):
    """A chip back at power-on defaults needs EX, RT and a configuration; done in one
    cycle that would cost 4.4 ms of the datasheet's waits, more than a cycle's slack.
    One step a cycle, no cycle overruns its bound by more than the costliest step."""
    scene = two_sensor_scene()
    scene.faults = [Fault("detach", 0.05, 0.1, address=0x0F)]
    clock = VirtualClock()
    bus = simulated_bus(scene, clock=clock, bus_hz=400e3)
    reader = Reader(
        bus,
        [MLX90393(bus, a, sleep=bus.sleep) for a in range(0x0C, 0x1C)],
        scheduler,
        mlx.Settings(),
        400e3,
        readback_every=0,
    )
    reader.start()
    bound = cycle_bound(
        scheduler, 16, mlx.Settings(), 400e3, bus.ioctl_s, readback=False, adapter=bus.adapter
    )
    clock.sleep(0.02)
    longest, back_at = 0.0, None
    while clock.now() < 0.6 and back_at is None:
        t0 = clock.now()
        results = reader.read()
        longest = max(longest, clock.now() - t0)
        if t0 > 0.1 and results[0x0F].ok:
            back_at = t0
        clock.wait_until(t0 + 0.01)  # 100 Hz
    assert back_at is not None and reader.health[0x0F].reinits == 1  # reset, not only read back
    # The costliest step, the configuration: 7 register transfers of 65 bits, 1.1 ms of
    # wire (1.5 ms with SB in burst), and at most 10 ioctls more than a cycle's (its
    # transfers and the verification reads) at their fixed cost. In one go the reset
    # would add 4.4 ms more.
    assert longest < bound.cycle_s + 1.6e-3 + 10 * bus.ioctl_s


def longest_identical_run(settings: mlx.Settings, field_lsb: float, cycles: int) -> int:
    """The longest run of repeated X, Y, Z words of a chip at rest, its field at
    ``field_lsb`` codes on every axis (an integer: the centre of a code, the worst case)."""
    field_t = np.array([field_lsb * settings.sensitivity_ut(a) * 1e-6 for a in "xyz"])
    bus = simulated_bus(StaticScene({0x0C: field_t}), clock=VirtualClock(), seed=3)
    chip = MLX90393(bus, 0x0C, sleep=bus.sleep)
    chip.reset()
    chip.configure(settings)
    words, run, longest = None, 0, 0
    for _ in range(cycles):
        chip.start_single()
        bus.sleep(settings.single_measurement_us() * 1.2e-6)
        m = chip.read_measurement()
        now = tuple(m.raw[a] for a in "xyz")
        run = run + 1 if now == words else 0
        words, longest = now, max(longest, run)
    return longest


def test_the_stuck_threshold_is_far_above_what_noise_gives_at_rest():
    settings = mlx.Settings()  # the paper's: 2-3 uT of noise on a 6-10 uT code
    n = stuck_cycles_for(settings)
    longest = longest_identical_run(settings, 40.0, 3000)
    assert 5 <= longest < n / 2  # runs happen, and stay well short of the threshold


def test_stuck_detection_is_off_where_noise_cannot_move_a_code():
    settings = mlx.Settings(osr=3, dig_filt=7)  # 0.2 uT of noise on a 6 uT code
    assert stuck_cycles_for(settings) == 0
    assert longest_identical_run(settings, 40.0, 300) == 299  # a healthy chip repeats itself


class StatusAudit:
    """Wraps a bus's ``i2c_rdwr`` and records every command (but RR) whose status byte the
    next command to the same chip overtakes (the datasheet: an SM's status is read back to
    get valid data; the emulator starts no SM whose status is not read), and counts the
    mode commands (SM, SB) sent."""

    def __init__(self, bus):
        self.inner, self.unread, self.overtaken = bus.i2c_rdwr, set(), []
        self.modes = {mlx.CMD_SM: 0, mlx.CMD_SB: 0}
        bus.i2c_rdwr = self

    def __call__(self, *msgs) -> None:
        self.inner(*msgs)  # a refused or NACKed ioctl has no reply read: not counted
        for m in msgs:
            data = bytes(m)
            if m.flags & I2C_M_RD:
                self.unread.discard(m.addr)
            elif data:  # (a zero-length write is a probe, no command)
                if m.addr in self.unread:
                    self.overtaken.append((m.addr, data[0]))
                if data[0] == mlx.CMD_RR:  # changes nothing: `probe_shapes` sends one unread by design
                    self.unread.discard(m.addr)
                else:
                    self.unread.add(m.addr)
                if data[0] & 0xF0 in self.modes:
                    self.modes[data[0] & 0xF0] += 1


@pytest.mark.parametrize("adapter", ["permissive", "bcm2835", "designware"])
@pytest.mark.parametrize("scheduler", ["naive", "overlapped", "burst"])
def test_every_command_has_its_status_read_at_start_and_after_a_recovery(scheduler, adapter):
    """Until 2026-11-26 `overlapped` on bcm2835 sent 15 chips' SMs as writes alone."""
    scene = two_sensor_scene()
    scene.faults = [Fault("detach", 0.3, 0.35, address=0x0F)]  # after the start (about 0.1 s)
    clock = VirtualClock()
    bus = simulated_bus(scene, clock=clock, bus_hz=400e3, adapter=adapter)
    audit = StatusAudit(bus)
    reader = Reader(
        bus, [MLX90393(bus, a, sleep=bus.sleep) for a in range(0x0C, 0x1C)], scheduler, mlx.Settings(), 400e3
    )
    assert reader.start() == {}
    first = reader.read()
    assert all(r.ok for r in first.values()), [hex(r.address) for r in first.values() if not r.ok]
    while clock.now() < 0.8:
        t0 = clock.now()
        results = reader.read()
        reader.upkeep()
        clock.wait_until(t0 + 0.01)
    assert reader.health[0x0F].reinits >= 1 and results[0x0F].ok  # reset, and back
    assert audit.overtaken == []
    assert audit.modes[mlx.CMD_SB if scheduler == "burst" else mlx.CMD_SM] > 16  # so it looked at some


@pytest.mark.parametrize(
    "oscillator,scheduler,adapter",
    [
        (o, s, a)
        for o in (0.8, 1.2)
        for s in ("naive", "overlapped", "burst")
        for a in ("permissive", "bcm2835", "designware")
    ],
)
def test_the_reader_reads_chips_at_either_end_of_the_oscillators_spread(scheduler, adapter, oscillator):
    """The datasheet's conversion times are nominal, +-20 %: the reader waits for the slowest
    (`OSC_MARGIN`), so every chip at 0.8 or 1.2 times nominal gives a reading every cycle,
    from the first, temperatures included (300 cycles, 16 chips). In burst mode the first
    read waits for the last-started chip's first result (`Reader.start`): without it, the
    read in one ioctl (permissive) came before 0x1B's at 1.2 and it was refused once."""
    clock = VirtualClock()
    bus = simulated_bus(two_sensor_scene(), clock=clock, bus_hz=400e3, adapter=adapter)
    for chip in bus.chips.values():
        chip.oscillator = oscillator
    reader = Reader(
        bus, [MLX90393(bus, a, sleep=bus.sleep) for a in range(0x0C, 0x1C)], scheduler, mlx.Settings(), 400e3
    )
    assert reader.start() == {}
    failed = []
    for cycle in range(300):
        t0 = clock.now()
        results = reader.read(mlx.ZYXT_XYZT if cycle % 10 == 0 else mlx.ZYXT_XYZ)
        failed += [(cycle, hex(r.address)) for r in results.values() if not r.ok]
        reader.upkeep()
        clock.wait_until(t0 + 0.01)
    assert failed == []
