"""The usual cycle in arrays (`acquire.readings.Readings`): what it holds is what the per-chip
path gives, chip by chip, whatever order the chips were read in and after faults; a stuck
chip found in it is an error like anywhere else; a sensor's flux taken from its rows is the
flux stacked from its chips' results."""

from __future__ import annotations

import numpy as np
import pytest

from ftsensord.acquire.health import ChipResult
from ftsensord.acquire.reader import Reader
from ftsensord.acquire.readings import Readings
from ftsensord.chip import mlx90393 as mlx
from ftsensord.chip.driver import MLX90393
from ftsensord.config.file import builtin_path, load_config
from ftsensord.errors import ChipProtocolError
from ftsensord.processing.filters import WrenchFilter
from ftsensord.processing.pipeline import SensorPipeline
from ftsensord.sim import StaticScene, VirtualClock, simulated_bus

ADDRESSES = list(range(0x0C, 0x1C))


def _scene() -> StaticScene:
    # Fields drawn over +-2 mT: a chip given another's row would be mT off.
    rng = np.random.default_rng(11)
    return StaticScene({a: rng.uniform(-2e-3, 2e-3, 3) for a in ADDRESSES}, dict.fromkeys(ADDRESSES, 30.0))


def _reader(scheduler: str, scene: StaticScene) -> Reader:
    bus = simulated_bus(scene, clock=VirtualClock(), bus_hz=400e3, seed=2)
    reader = Reader(
        bus,
        [MLX90393(bus, a, sleep=bus.sleep) for a in ADDRESSES],
        scheduler,
        mlx.Settings(),
        readback_every=1,
    )
    assert reader.start() == {}
    return reader


def _cycle(reader: Reader) -> Readings:
    t0 = reader.bus.monotonic()
    readings = reader.read()
    reader.upkeep()
    reader.bus.sleep(max(0.0, t0 + 0.01 - reader.bus.monotonic()))  # 100 Hz: time for every burst's result
    return readings


@pytest.mark.parametrize("scheduler", ["burst", "overlapped"])
def test_a_clean_cycle_holds_what_each_chip_replied(scheduler):
    """Read back every cycle (burst: that chip read last, a new order each cycle), then a chip
    whose register changed, found by the read-back, reset and configured again (its settings
    new: a new plan built): every clean cycle's rows are each chip's own reply, decoded as
    the per-chip decoder decodes it, and the cycles are clean again once it is back."""
    scene = _scene()
    reader = _reader(scheduler, scene)
    clean_after = 0  # clean cycles after the chip came back
    for k in range(100):
        if k == 20:
            reader.bus.chips[0x13].registers[0] = 0x007C  # CONF1's GAIN_SEL changed by itself
        found_before = reader.health[0x13].register_drifts  # the read-back comes after the read
        readings = _cycle(reader)
        assert list(readings) == ADDRESSES and len(readings) == len(ADDRESSES)
        if not readings.clean:
            assert k >= 20  # nothing but the fault takes a cycle out of arrays here
            continue
        clean_after += reader.health[0x13].reinits == 1
        (plan,) = reader.xfer._plans.values()
        for i, (a, chip) in enumerate(zip(ADDRESSES, reader.chips)):
            m = readings[a].measurement
            want = chip.decode_measurement(bytes(plan.block[i]))
            np.testing.assert_array_equal(m.field_t, want.field_t)
            assert m.words == want.words and m.status == want.status and not m.any_saturated
            drifted = a == 0x13 and k >= 20 and not found_before  # read at the wrong gain until read back
            assert m.temperature_c is None and (
                drifted or np.allclose(m.field_t, scene.field_t(a, 0.0), atol=50e-6)
            )
    assert reader.health[0x13].register_drifts == 1
    assert clean_after >= 50 and readings.clean and not reader.failing


def test_a_cycle_with_a_failing_chip_is_given_chip_by_chip():
    reader = _reader("burst", _scene())
    _cycle(reader)
    reader.bus.faults.nack(0x13)
    for _ in range(3):
        readings = _cycle(reader)
    assert not readings.clean and readings.field is None
    assert not readings[0x13].ok and all(readings[a].ok for a in ADDRESSES if a != 0x13)


def test_a_chip_stuck_in_a_clean_cycle_becomes_its_error():
    """The stuck test on the words of a clean cycle: the limit's cycle gives that chip's error, and
    the others stay as read."""
    reader = _reader("burst", _scene())
    reader.care.stuck_cycles = 5
    reader.bus.chips[0x0E].stuck = True
    outcomes = [_cycle(reader) for _ in range(12)]
    found = [r for r in outcomes if 0x0E in r and not r[0x0E].ok]
    assert found, "the stuck chip was never found"
    first = found[0]
    assert isinstance(first[0x0E].error, ChipProtocolError) and "stuck" in str(first[0x0E].error)
    assert not first.clean and all(first[a].ok for a in ADDRESSES if a != 0x0E)
    assert reader.health[0x0E].stuck_detections == 1


@pytest.mark.parametrize("interleaved", [False, True])
def test_a_sensors_rows_are_its_chips_flux(interleaved):
    """A sensor's flux from a clean cycle's rows equals the flux stacked from its chips' results,
    its chips consecutive or not (every other address: rows that are no slice)."""
    config = load_config(builtin_path("sim.toml"))
    s = config.sensors[0]
    addresses = tuple(ADDRESSES[1::2]) if interleaved else tuple(ADDRESSES[8:])
    s.addresses = addresses
    readings = _cycle(_reader("burst", _scene()))
    assert readings.clean
    assert isinstance(readings.rows(addresses), slice) is not interleaved
    by_dict = {a: readings[a] for a in ADDRESSES}  # the per-chip results, no arrays
    fast = SensorPipeline.build(s, WrenchFilter(), 2)
    slow = SensorPipeline.build(s, WrenchFilter(), 2)
    flux, flags, usable = fast.flux(readings)
    want, want_flags, want_usable = slow.flux(by_dict)
    np.testing.assert_array_equal(flux, want)
    assert flags == want_flags == 0 and usable.all() and want_usable.all()
    np.testing.assert_array_equal(fast.last_flux, slow.last_flux)


def test_a_failed_chip_takes_the_cycle_out_of_arrays():
    readings = _cycle(_reader("burst", _scene()))
    error = ChipResult(0x0C, error=ChipProtocolError(0x0C, "stuck"))
    kept = readings[0x0D].measurement.field_t.copy()
    readings.fail(0x0C, error)
    assert readings.field is None and readings[0x0C] is error
    np.testing.assert_array_equal(readings[0x0D].measurement.field_t, kept)
    with pytest.raises(KeyError):
        readings[0x40]


def test_the_healthy_chips_follow_every_chip_that_fails_and_comes_back():
    """`ChipCare.healthy` keeps one list while no chip starts or stops failing: a chip taken
    out leaves it at once, and it is in it again once it is back, read from the next cycle."""
    reader = _reader("burst", _scene())
    care = reader.care
    first = care.healthy(reader.chips)
    assert first == reader.chips and care.healthy(reader.chips) is first
    care.fail(0x13, reader.bus.monotonic(), reset=True, why="test")
    out = care.healthy(reader.chips)
    assert [c.address for c in out] == [a for a in ADDRESSES if a != 0x13]
    for _ in range(20):  # one reset step a cycle (EX, RT, configure), then back
        readings = _cycle(reader)
        if not care.health[0x13].failing:
            break
    assert not care.health[0x13].failing
    assert [c.address for c in care.healthy(reader.chips)] == ADDRESSES
    assert _cycle(reader)[0x13].ok and _cycle(reader).clean
    assert 0x13 not in readings or not readings[0x13].ok  # the cycle it came back in gave no data
