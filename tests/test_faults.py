"""Every fault of the simulated bus, scripted from a scene, through the daemon:
it never stops, every affected sample is flagged, and it recovers on its own."""

from __future__ import annotations

import errno

import numpy as np
import pytest

from ftsensord.acquire.bound import cycle_bound
from ftsensord.protocol import wire
from ftsensord.sim import Fault, load_scene
from ftsensord.sim.faults import random_faults

from .conftest import assert_names_file_and_key
from .test_daemon import LOAD, Rig


def fault(kind: str, at: float, until: float | None = None, **extra) -> str:
    lines = ["[[fault]]", f'kind = "{kind}"', f"at_s = {at}"]
    if until is not None:
        lines.append(f"until_s = {until}")
    lines += [f"{k} = {v}" for k, v in extra.items()]
    return "\n" + "\n".join(lines) + "\n"


def run(tmp_path, scene_extra: str, seconds: float, **config) -> tuple[Rig, dict[str, list[wire.Sample]]]:
    rig = Rig(tmp_path, scene_extra=scene_extra, **config)
    out = rig.cycles(int(seconds * 100))
    return rig, out


def window(samples: list[wire.Sample], start: float, end: float) -> list[wire.Sample]:
    return [s for s in samples if start <= s.t_mono < end]


def test_transient_nack_degrades_then_recovers_within_a_second(tmp_path):
    rig, out = run(tmp_path, fault("nack", 0.3, 0.6, address=0x0E), 2.0)
    w = out["wrench/sensor1"]
    during = window(w, 0.32, 0.6)
    assert during and all(s.flags & wire.FLAG_CHIP_MISSING and s.flags & wire.FLAG_DEGRADED for s in during)
    recovered = next(s for s in w if s.t_mono > 0.6 and s.flags == 0)
    assert recovered.t_mono - 0.6 < 1.0
    assert [s.seq for s in w] == list(range(len(w)))  # no publish cycle lost
    rig.close()


def test_a_chip_that_disappears_and_returns_at_power_on_defaults_is_reinitialised(tmp_path):
    rig, out = run(tmp_path, fault("detach", 0.2, 0.5, address=0x14), 2.0)
    w = out["wrench/sensor2"]
    assert all(s.flags & wire.FLAG_CHIP_MISSING for s in window(w, 0.22, 0.5))
    back = next(s for s in w if s.t_mono > 0.5 and s.flags == 0)
    assert back.t_mono - 0.5 < 1.0
    assert rig.daemon.reader.health[0x14].reinits >= 1
    assert np.allclose(np.mean([s.values for s in w[-50:]], axis=0)[:3], 0, atol=0.3)  # correct again
    rig.close()


@pytest.mark.parametrize("kind", ["io_error", "timeout"])
def test_a_bus_wide_error_flags_every_sensor_and_the_loop_goes_on(tmp_path, kind):
    rig, out = run(tmp_path, fault(kind, 0.3, 0.35), 2.0)
    for topic in ("wrench/sensor1", "wrench/sensor2"):
        hit = window(out[topic], 0.3, 0.35)
        assert hit and all(s.flags & wire.FLAG_CHIP_MISSING for s in hit)
        assert out[topic][-1].flags == 0
        assert [s.seq for s in out[topic]] == list(range(200))
    rig.close()


def test_a_stuck_chip_is_detected_flagged_and_reinitialised(tmp_path):
    rig, out = run(tmp_path, fault("stuck", 0.2, 3.0, address=0x0F), 3.5, extra="stuck_cycles = 50")
    w = out["wrench/sensor1"]
    first = next(s for s in w if s.flags & wire.FLAG_CHIP_MISSING)
    # After 50 identical cycles. The chip's noise (2-3 uT) is under its LSB (6-10 uT), so
    # the readings just before the fault may already be the frozen one (two in a row alike:
    # about one in five here): the run of identical readings may begin a cycle or two early
    # (this scene: one).
    assert 0.2 + 0.5 - 0.03 <= first.t_mono < 0.2 + 0.6
    assert rig.daemon.reader.health[0x0F].stuck_detections >= 1
    assert w[-1].flags == 0  # after the fault, fresh data again
    rig.close()


@pytest.mark.parametrize("scheduler", ["overlapped", "burst"])
def test_a_register_the_chip_accepts_silently_is_found_by_read_back(tmp_path, scheduler):
    # CONF1 to GAIN_SEL 7: the chip converts happily, at a fifth of the expected LSB.
    rig, out = run(
        tmp_path,
        fault("drift_register", 0.3, address=0x10, register=0, value=0x007C),
        1.0,
        extra=f'scheduler = "{scheduler}"',
    )
    assert rig.config.readback_every == 1  # burst at 100 Hz has the time (test_config_...burst...)
    assert not any(s.flags & wire.FLAG_STALE for s in out["wrench/sensor1"])
    h = rig.daemon.reader.health[0x10]
    assert h.register_drifts == 1 and h.reinits == 1
    w = out["wrench/sensor1"]
    found = next(s for s in w if s.t_mono > 0.3 and s.flags & wire.FLAG_CHIP_MISSING)
    assert found.t_mono - 0.3 <= 0.17  # one chip read back a cycle: each within 16 cycles
    assert w[-1].flags == 0 and np.allclose(
        np.mean([s.values for s in w[-30:]], axis=0)[:3], LOAD[:3], atol=0.3
    )
    rig.close()


def test_a_register_change_the_chip_refuses_to_work_with_is_caught_at_once(tmp_path):
    # CONF3 to 0: OSR 0, DIG_FILT 0 is forbidden; the emulated chip refuses SM at once.
    rig, out = run(tmp_path, fault("drift_register", 0.3, address=0x10, register=2, value=0), 1.0)
    w = out["wrench/sensor1"]
    found = next(s for s in w if s.t_mono > 0.3 and s.flags & wire.FLAG_CHIP_MISSING)
    assert found.t_mono - 0.3 <= 0.02 and rig.daemon.reader.health[0x10].reinits == 1
    assert w[-1].flags == 0
    rig.close()


def test_a_saturated_chip_is_flagged_while_it_lasts(tmp_path):
    rig, out = run(tmp_path, fault("saturate", 0.2, 0.4, address=0x12, field_mt=70), 1.0)
    w = out["wrench/sensor1"]
    during = window(w, 0.21, 0.4)
    assert during and all(s.flags & wire.FLAG_SATURATED and s.flags & wire.FLAG_DEGRADED for s in during)
    assert all(np.allclose(s.values[:3], LOAD[:3], atol=0.4) for s in during)
    assert w[-1].flags == 0
    rig.close()


def test_a_slow_bus_lengthens_cycles_but_loses_nothing(tmp_path):
    rig = Rig(tmp_path, scene_extra=fault("slow", 0.0, 10.0, factor=1.5))
    t0 = rig.clock.now()
    rig.daemon.cycle()  # the first cycle reads the temperature too
    # The wire takes 1.5 times as long; the chips' conversions do not.
    slow = cycle_bound(
        "overlapped",
        16,
        rig.config.settings,
        400e3 / 1.5,
        rig.bus.ioctl_s,
        temperature=True,
        adapter=rig.bus.adapter,
    )
    # Within 1 %: the reader times its wait by the configured bus, so a slower wire
    # shortens it by a fraction of a byte (still safe: the RM's own bits come first).
    assert rig.clock.now() - t0 == pytest.approx(slow.cycle_s, rel=0.01)
    assert slow.cycle_s > rig.daemon.period_s  # so at 100 Hz this bus makes every cycle late
    rig.close()


def test_fault_files_name_the_key_at_fault(tmp_path):
    from .test_daemon import SCENE

    path = tmp_path / "s.toml"
    for extra, key, expected in (
        (fault("nack", 0.1, 0.2), "fault[0].address", "missing"),
        (fault("melt", 0.1), "fault[0].kind", "one of"),
        (fault("nack", 0.3, 0.2, address=0x0C), "fault[0].until_s", "after at_s"),
        (fault("nack", 0.1, 0.2, address=0x1B, colour=1), "fault[0].colour", "one of"),
    ):
        path.write_text(SCENE + extra)
        assert_names_file_and_key(load_scene, path, key, expected)


def test_random_fault_schedules_are_valid_and_varied():
    faults = random_faults(list(range(0x0C, 0x1C)), 600.0, np.random.default_rng(1))
    assert len(faults) > 30 and len({f.kind for f in faults}) == 8
    assert all(isinstance(f, Fault) and f.until_s > f.at_s for f in faults)
    assert errno.EIO  # the bus-wide kinds map onto the kernel's errnos in FaultScript
