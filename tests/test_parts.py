"""The daemon's parts, each on its own: loop timing on a virtual clock, chip health,
the chip ledger, and control requests against a stand-in for the daemon."""

from __future__ import annotations

import json

import numpy as np
import pytest

from ftsensord.acquire.health import ChipCare, ChipResult
from ftsensord.chip import mlx90393 as mlx
from ftsensord.chip.driver import MLX90393, Measurement
from ftsensord.daemon.control import Control
from ftsensord.daemon.loop import LATE_FRACTION, LoopTiming
from ftsensord.daemon.status import ChipLedger
from ftsensord.errors import ChipRefusedError
from ftsensord.sim import VirtualClock, simulated_bus, two_sensor_scene


# --- loop timing -------------------------------------------------------------------------
def test_deadlines_a_whole_period_behind_are_skipped_and_counted_never_made_up():
    t = LoopTiming()
    period = 0.01
    deadline, lateness = t.skip_missed(0.0, 0.035, period)  # 3.5 periods late
    assert t.missed == 3 and deadline == pytest.approx(0.03) and lateness == pytest.approx(0.005)
    deadline, lateness = t.skip_missed(0.04, 0.0405, period)  # on time, within the period
    assert t.missed == 3 and deadline == 0.04 and lateness == pytest.approx(0.0005)


def test_a_cycle_is_late_past_a_tenth_of_its_period_and_the_rate_follows_the_starts():
    t, period = LoopTiming(), 0.01
    assert not t.begin(0.0, LATE_FRACTION * period * 0.99, period)
    assert t.begin(0.01, LATE_FRACTION * period * 1.01, period) and t.late == 1
    assert t.achieved_rate_hz() == pytest.approx(100.0)
    t.end(0.004)
    assert t.cycles == 1 and list(t.durations) == [0.004]


def test_no_rate_before_two_cycles():
    t = LoopTiming()
    assert t.achieved_rate_hz() is None
    t.begin(1.0, 0.0, 0.01)
    assert t.achieved_rate_hz() is None


# --- chip health ------------------------------------------------------------------------------
def _measurement(words: tuple[int, int, int]) -> Measurement:
    return Measurement(mlx.Status(0x02), np.zeros(3), np.zeros(3, dtype=bool), None, tuple(words))


def _care(stuck_cycles: int) -> tuple[ChipCare, VirtualClock]:
    clock = VirtualClock()
    bus = simulated_bus(two_sensor_scene(), clock=clock)
    return ChipCare(
        bus, [MLX90393(bus, 0x0C, sleep=bus.sleep)], mlx.Settings(), burst=False, stuck_cycles=stuck_cycles
    ), clock


def test_identical_words_for_the_stuck_count_make_a_chip_fail_with_a_reset_due():
    care, clock = _care(stuck_cycles=3)
    for _ in range(3):
        assert care.judge(ChipResult(0x0C, _measurement((1, 2, 3))), clock.now()).ok  # 0, 1, 2 repeats
    stuck = care.judge(ChipResult(0x0C, _measurement((1, 2, 3))), clock.now())
    assert not stuck.ok and "stuck" in str(stuck.error)
    h = care.health[0x0C]
    assert h.failing and h.needs_reset and h.stuck_detections == 1 and care.failing == {0x0C}


def test_moving_words_never_look_stuck():
    care, clock = _care(stuck_cycles=3)
    assert all(care.judge(ChipResult(0x0C, _measurement((i, 2, 3))), clock.now()).ok for i in range(50))
    assert not care.failing


def test_no_new_data_is_stale_for_a_while_then_a_failure():
    care, clock = _care(stuck_cycles=0)
    stale = ChipRefusedError(0x0C, "no new data", mlx.Status(0x10), command="RM")
    from ftsensord.acquire.health import STALE_LIMIT

    for _ in range(STALE_LIMIT):
        care.judge(ChipResult(0x0C, error=stale), clock.now())
    assert not care.failing
    care.judge(ChipResult(0x0C, error=stale), clock.now())
    assert care.failing == {0x0C}


def test_backoff_doubles_up_to_its_ceiling():
    from ftsensord.acquire.health import BACKOFF_FIRST_S, BACKOFF_MAX_S

    care, _ = _care(stuck_cycles=0)
    care.fail(0x0C, 0.0)
    assert care.health[0x0C].retry_at == 0.0  # the first retry: the next cycle
    waits = []
    for _ in range(8):
        care.fail(0x0C, 0.0)
        waits.append(care.health[0x0C].backoff_s)
    assert waits[0] == BACKOFF_FIRST_S and waits[1] == 2 * BACKOFF_FIRST_S and waits[-1] == BACKOFF_MAX_S


# --- the chip ledger ---------------------------------------------------------------------------------
def test_the_ledger_counts_stale_apart_from_failures():
    ledger = ChipLedger({"s": (0x0C, 0x0D)})
    ledger.count(ChipResult(0x0C, error=ChipRefusedError(0x0C, "no data", mlx.Status(0x10), command="RM")))
    ledger.count(ChipResult(0x0D, error=ChipRefusedError(0x0D, "refused", mlx.Status(0x10), command="SM")))
    assert ledger.chips[0x0C].stale == 1 and ledger.chips[0x0C].ok
    assert ledger.chips[0x0D].errors == 1 and not ledger.chips[0x0D].ok and ledger.failing == 1
    ledger.count(ChipResult(0x0D, _measurement((1, 2, 3))))
    assert ledger.failing == 0


# --- control, against a stand-in for the daemon --------------------------------------------------------
class StandIn:
    """What control requests act on, recording what they asked."""

    sensor_names = ["sensor1", "sensor2"]

    def __init__(self) -> None:
        self.calls: list[tuple] = []

    def status(self):
        return {"cycles": 7}

    def request_tare(self, envelope, sensors, samples):
        self.calls.append(("tare", sensors, samples))

    def request_reload(self, envelope):
        raise ValueError("the new file is bad")

    def loop_settings(self):
        return 100.0, 1, 0.0

    def set_loop(self, rate_hz, averaging, lowpass_hz):
        self.calls.append(("set", rate_hz, averaging, lowpass_hz))
        return {"rate_hz": rate_hz}

    def set_estimator(self, estimator, sensor):
        self.calls.append(("estimator", estimator, sensor))
        return {}

    def __getattr__(self, name):  # any command added later answers plainly
        return lambda *a, **k: {}


def ask(control: Control, **request) -> dict | None:
    return control.handle(json.dumps(request).encode(), [b"peer"])


def test_control_dispatches_checked_arguments_to_the_daemon():
    target = StandIn()
    control = Control(None, target)
    assert ask(control, cmd="status") == {"ok": True, "result": {"cycles": 7}}
    assert ask(control, cmd="tare", samples=5, sensor="sensor2") is None  # answered when done
    assert ask(control, cmd="set", lowpass_hz=10) == {"ok": True, "result": {"rate_hz": 100.0}}
    assert ask(control, cmd="set", estimator="nonlinear") == {"ok": True, "result": {}}
    assert target.calls == [
        ("tare", ["sensor2"], 5),
        ("set", 100.0, 1, 10.0),
        ("estimator", "nonlinear", None),
    ]


@pytest.mark.parametrize(
    ("request_", "error"),
    [
        ({"cmd": "tare", "sensor": "sensor9"}, "sensor9"),
        ({"cmd": "set", "rate_hz": True}, "rate_hz"),
        ({"cmd": "set", "lowpass_hz": 60}, "below half the rate"),
        ({"cmd": "set", "estimator": "magic"}, "estimator"),
        ({"cmd": "set", "sensor": "sensor1", "rate_hz": 50}, "sensor"),
        ({"cmd": "reload"}, "the new file is bad"),
    ],
)
def test_control_refuses_what_the_daemon_must_not_see(request_, error):
    target = StandIn()
    reply = ask(Control(None, target), **request_)
    assert reply is not None and reply["ok"] is False and error in reply["error"]
    assert target.calls == []


# --- calibrations kept across reloads ------------------------------------------------------------
def test_a_reload_reuses_an_unchanged_calibration_and_reads_a_changed_one(tmp_path):
    from pathlib import Path

    from ftsensord.config.file import load_config
    from ftsensord.config.sensors import Calibrations
    from ftsensord.errors import ConfigError

    packaged = Path(__file__).resolve().parent.parent / "ftsensord" / "data" / "sim-sensor1.json"
    path = tmp_path / "cal.json"
    path.write_bytes(packaged.read_bytes())
    cache = Calibrations()
    first = cache.load(path)
    assert cache.load(path) is first  # unchanged: not read again
    doc = json.loads(path.read_text())
    doc["sensor"]["serial"] = doc["sensor"]["serial"][::-1]  # same size, other content
    from ftsensord.calibration.calfile import checksum

    doc["checksum"] = checksum(doc)
    path.write_text(json.dumps(doc, indent=1) + "\n")
    again = cache.load(path)
    assert again is not first and again.serial == first.serial[::-1]
    path.unlink()
    with pytest.raises(ConfigError, match=str(path)):
        cache.load(path)
    # The daemon's reload goes through it: the configuration's own calibrations are remembered.
    config = load_config()
    cal = config.sensors[0]
    assert Calibrations().remember(config.sensors).load(cal.calibration_path) is cal.calibration
