"""The silicone's memory: the Prony series' creep, the scene's deflection under a held
load, and the recursive inverse that undoes it."""

from __future__ import annotations

import numpy as np
import pytest

from ftsensord.daemon.status import sensor_status
from ftsensord.model import se3
from ftsensord.model.viscoelastic import CreepFilter, CreepInverse, Relaxation
from ftsensord.sim import load_scene
from ftsensord.sim.loads import RecordedLoad, StaticLoad, StepLoad
from ftsensord.sim.memory import DEFAULT_RELAXATION
from ftsensord.sim.physics import PAPER_STIFFNESS_DIAG, PhysicalScene, SimSensor

from .conftest import assert_names_file_and_key

SERIES = Relaxation.from_pairs(DEFAULT_RELAXATION)
# A series that creeps more and sooner than the default (the one used before the default was
# fitted to a published loss): its creep shows within a few seconds' run, where the default's
# fast 2.5 % is gone within one and its slow 5 % has barely begun.
HARSH = Relaxation.from_pairs(((0.10, 1.0), (0.05, 30.0)))
ADDRESSES = tuple(range(0x0C, 0x14))


def test_one_term_creeps_as_the_standard_linear_solid():
    # G(t) = K0 (1 - g (1 - e^-t/tau)): held under a load it creeps with rho = tau / (1 - g)
    # from (1 - g) of the final deflection (a textbook closed form, not our eigen-solve).
    r = Relaxation((0.2,), (1.5,))
    c, rho = r.creep
    assert c == pytest.approx([0.2]) and rho == pytest.approx([1.5 / 0.8])
    t = np.array([0.0, 1.0, 10.0])
    assert r.creep_response(t) == pytest.approx(1 - 0.2 * np.exp(-t / 1.875))


def test_creep_of_the_series_holds_the_load_through_the_relaxation_integral():
    # Boltzmann: w(t) = K0 sum_j G(t - s_j) dxi_j. The creep the series predicts for a held load,
    # put through the relaxation modulus itself, must give that load back at every time.
    r = Relaxation.from_pairs([[0.1, 0.8], [0.08, 4.0], [0.05, 30.0]])
    dt, t_end = 2e-3, 20.0
    s = np.arange(0.0, t_end, dt)
    xi = r.creep_response(s) / r.g_inf  # K0 xi / w, as K_inf = g_inf K0
    dxi = np.diff(np.concatenate([[0.0], xi]))
    for t in (0.5, 3.0, 19.0):
        j = s <= t
        w = np.sum(r.modulus(t - s[j]) * dxi[j])
        assert w == pytest.approx(1.0, abs=2e-3)  # 2e-3: the sum's first-order error at 2 ms steps


def _scene(load, relaxation=SERIES) -> PhysicalScene:
    return PhysicalScene([SimSensor("s", ADDRESSES, load=load, relaxation=relaxation)], crosstalk="off")


def test_a_held_step_deflects_as_the_closed_form():
    w = np.array([2.0, 0.0, -1.0, 0.0, 0.01, 0.0])
    scene = _scene(StepLoad(1.0, np.zeros(6), w))
    reference = PhysicalScene([SimSensor("s", ADDRESSES)], crosstalk="off")
    sensor = scene.sensors[0]
    for t in (0.5, 1.0, 1.2, 2.0, 5.0, 31.0, 120.0):
        got = np.array([scene.field_t(a, t) for a in ADDRESSES])
        creep = 0.0 if t < 1.0 else SERIES.creep_response(t - 1.0)
        xi = sensor.deflection(w * creep)  # K_inf xi(t) = w (1 - sum c e^-t/rho)
        want = reference.chip_fields(sensor.geometry, se3.exp_se3(xi))
        assert np.allclose(got, want, rtol=0, atol=1e-12), t  # 1e-12 T: the same arithmetic, round-off
    # The instantaneous deflection is g_inf of the held one: stiffness_diag is the long-term stiffness.
    assert SERIES.creep_response(0.0) == pytest.approx(SERIES.g_inf)


def test_a_static_scene_keeps_no_memory_and_reads_as_before():
    w = np.array([1.0, 2.0, 0.0, 0.0, 0.0, 0.02])
    plain = PhysicalScene([SimSensor("s", ADDRESSES, load=StaticLoad(w))], crosstalk="off")
    assert plain.sensors[0].memory is None
    held = _scene(StaticLoad(w))  # a load in place for ever: fully crept from the first reading
    for t in (0.0, 3.0):
        assert np.allclose(held.field_t(0x0C, t), plain.field_t(0x0C, t), atol=1e-15)


def test_the_inverse_recovers_a_step_and_sinusoids():
    # The scene's filter at 1 ms (load held over each step), sampled at 100 Hz by the daemon's inverse.
    for f_hz in (0.0, 0.5, 5.0):
        forward, inverse = CreepFilter(SERIES, 1e-3, 1), CreepInverse(SERIES, 1e-2, width=1)
        got, truth, raw = [], [], []
        for k in range(20_000):
            t = k * 1e-3
            w = np.array([2.0 * (np.sin(2 * np.pi * f_hz * t) if f_hz else float(t >= 5.0))])
            if k % 10 == 0:
                y = forward.output(w)
                got.append(inverse.apply(y)[0])
                raw.append(y[0])
                truth.append(w[0])
            forward.advance(w)
        got, truth, raw = np.array(got), np.array(truth), np.array(raw)
        after = slice(550, None) if not f_hz else slice(100, None)  # a step: from 0.5 s after it on
        # 1 % of 2 N: what the issue asks (2 %) with margin for the 1 ms / 10 ms sampling's mismatch.
        assert np.abs(got - truth)[after].max() < 0.02, f_hz
        assert np.abs(raw - truth)[after].max() > 0.1, f_hz  # and without the inverse it was far off


def test_the_inverse_starts_afresh_after_a_reset():
    inverse = CreepInverse(SERIES, 1e-2, width=1)
    for _ in range(50):
        inverse.apply(np.array([0.0]))
    inverse.apply(np.array([1.7]))  # a step's first sample: the inverse reads more than 1.7
    inverse.reset()
    assert inverse.apply(np.array([1.7]))[0] == pytest.approx(1.7)  # a load long held, nothing carried
    assert inverse.apply(np.array([1.7]))[0] == pytest.approx(1.7)


@pytest.mark.parametrize(
    "relaxation, expected",
    [
        ("[[0.5, 1.0], [0.5, 2.0]]", "summing below 0.9"),
        ("[[0.1, -1.0]]", "times > 0"),
        ("[[0.1]]", "pairs [fraction, time_s]"),
        ("0.1", "pairs [fraction, time_s]"),
    ],
)
def test_a_bad_series_is_refused_naming_file_and_key(tmp_path, relaxation, expected):
    path = tmp_path / "scene.toml"
    path.write_text(
        f'version = 1\nkind = "sensors"\n[[sensor]]\naddresses = {list(ADDRESSES)}\n'
        f"[sensor.silicone]\nrelaxation = {relaxation}\n"
    )
    assert_names_file_and_key(load_scene, path, "relaxation", expected)


def test_a_scene_file_asks_for_the_memory_and_gets_the_default(tmp_path):
    path = tmp_path / "scene.toml"
    path.write_text(
        f'version = 1\nkind = "sensors"\n[[sensor]]\naddresses = {list(ADDRESSES)}\n'
        f"[sensor.silicone]\n[[sensor]]\naddresses = {list(range(0x14, 0x1C))}\n"
    )
    scene = load_scene(path)
    assert isinstance(scene, PhysicalScene)
    assert scene.sensors[0].relaxation == SERIES and scene.sensors[1].memory is None
    assert np.allclose(scene.sensors[0].stiffness, np.diag(PAPER_STIFFNESS_DIAG))


def test_a_moving_load_is_integrated_step_by_step():
    # A ramp from 0 to 2 N over 2 s, read once at its end: the state integrated every step, not
    # jumped with the last load (which would read as if 2 N had been held for 2 s).
    scene = _scene(RecordedLoad(np.array([0.0, 2.0]), np.array([np.zeros(6), [2.0, 0, 0, 0, 0, 0]])))
    scene.field_t(0x0C, 0.0)
    memory = scene.sensors[0].memory
    assert memory is not None
    forward = CreepFilter(SERIES, 1e-3, 6)
    forward.settle(np.zeros(6))
    for k in range(2000):
        forward.advance(np.array([2.0 * k / 2000, 0, 0, 0, 0, 0]))
    scene.field_t(0x0C, 2.0)
    assert np.allclose(memory.filter.p, forward.p, atol=1e-12)


# --- identification and the daemon's stage ---------------------------------------------------
def _part_with_memory(relaxation: Relaxation) -> PhysicalScene:
    """The default scene's sensor1 (the part the packaged calibration was fitted on), its silicone
    given ``relaxation``."""
    from ftsensord.sim.scene import default_scene

    scene = default_scene()
    sensor = scene.sensors[0]
    sensor.relaxation = relaxation
    return PhysicalScene(
        scene.sensors,
        field_model=scene.field_model,
        crosstalk=scene.crosstalk,
        external_field_t=scene.external_field_t,
    )


def _packaged_calibration():
    from ftsensord.calibration.calfile import Calibration
    from ftsensord.protocol.paths import builtin_path

    return Calibration.load(builtin_path("sim-sensor1.json"))


def test_the_relaxation_is_identified_from_a_simulated_step_and_hold():
    from ftsensord.calibration.procedure import hold_poses
    from ftsensord.calibration.relaxation import identify
    from ftsensord.calibration.rig import record_hold, simulated_robot
    from ftsensord.sim import simulated_bus

    # A faster series than the default, so that a short hold shows both terms (the benchmark
    # identifies the default from the full procedure: docs/results/accuracy.md).
    truth = Relaxation.from_pairs([[0.10, 0.3], [0.05, 4.0]])
    scene = _part_with_memory(truth)
    bus = simulated_bus(scene, seed=3)
    hold = record_hold(
        bus,
        ADDRESSES,
        hold_poses(),
        simulated_robot(scene, "sensor1")["apply_load"],
        hold_s=12.0,
        period_s=0.01,
    )
    found, line = identify(hold, _packaged_calibration().model.wrench)
    assert found is not None, line
    got = found.relaxation
    # 20 %: what the issue asks of the identification, for each fraction and time.
    assert np.allclose(got.fractions, truth.fractions, rtol=0.2), line
    assert np.allclose(got.times_s, truth.times_s, rtol=0.2), line


def test_a_part_without_a_memory_identifies_no_relaxation_and_one_term_is_not_taken_for_two():
    from ftsensord.calibration.procedure import hold_poses
    from ftsensord.calibration.relaxation import identify
    from ftsensord.calibration.rig import record_hold, simulated_robot
    from ftsensord.sim import simulated_bus
    from ftsensord.sim.scene import default_scene

    def hold_of(scene: PhysicalScene):
        bus = simulated_bus(scene, seed=5)
        robot = simulated_robot(scene, "sensor1")["apply_load"]
        return record_hold(bus, ADDRESSES, hold_poses(), robot, hold_s=12.0, period_s=0.01)

    # A perfect spring: the readings' noise alone, which a term's free time can always bend a little.
    found, line = identify(hold_of(default_scene()), _packaged_calibration().model.wrench)
    assert found is None and "no relaxation the readings resolve" in line and "noise alone" in line, line
    # One term (1 % at 0.5 s): resolved, and a second one, which noise alone would give, is not added.
    one = Relaxation.from_pairs([[0.01, 0.5]])
    found, line = identify(hold_of(_part_with_memory(one)), _packaged_calibration().model.wrench)
    assert found is not None and len(found.relaxation.fractions) == 1, line
    assert abs(found.relaxation.fractions[0] / 0.01 - 1) < 0.3, line  # 30 %: a 1 % creep in 12 s of noise


def test_a_hold_without_a_step_identifies_nothing_and_says_why():
    from ftsensord.calibration.dataset import Hold
    from ftsensord.calibration.relaxation import identify

    w = np.array([1.0, 0, 0, 0, 0, 0])
    hold = Hold(np.array([0.0, 1.0]), np.array([w, w]), np.linspace(0, 2, 50), np.zeros((50, 6)))
    found, line = identify(hold, lambda b: b)
    assert found is None and "do not change" in line


def _pipeline(silicone_scale: float = 1.0, series: Relaxation = SERIES):
    from dataclasses import replace

    from ftsensord.calibration.relaxation import SiliconeCalibration
    from ftsensord.config.sensors import SensorConfig
    from ftsensord.processing.filters import WrenchFilter
    from ftsensord.processing.pipeline import SensorPipeline

    cal = replace(_packaged_calibration(), silicone=SiliconeCalibration(series, silicone_scale, 0.0))
    config = SensorConfig("sensor1", ADDRESSES, __import__("pathlib").Path("sim-sensor1.json"), cal, "sensor")
    return SensorPipeline.build(config, WrenchFilter(), 2, thermal=False, rate_hz=100.0)


def _results(flux: np.ndarray, missing: int | None = None) -> dict:
    from ftsensord.acquire.health import ChipResult
    from ftsensord.chip import mlx90393 as mlx
    from ftsensord.chip.driver import Measurement
    from ftsensord.errors import ChipNotRespondingError

    out = {}
    for i, a in enumerate(ADDRESSES):
        if i == missing:
            out[a] = ChipResult(a, error=ChipNotRespondingError(a, "no answer"))
        else:
            out[a] = ChipResult(
                a, Measurement(mlx.Status(0x02), flux[3 * i : 3 * i + 3], np.zeros(3, dtype=bool), None, {})
            )
    return out


def _fluxes(scene: PhysicalScene, times: np.ndarray) -> np.ndarray:
    return np.array([np.concatenate([scene.field_t(a, t) for a in ADDRESSES]) for t in times])


def test_the_daemon_stage_undoes_a_held_steps_creep_and_restarts_on_a_tare_and_a_fault():
    from ftsensord.protocol import wire

    w = np.array([2.0, 0, 0, 0, 0, 0])
    scene = _part_with_memory(HARSH)
    scene.set_load("sensor1", StepLoad(1.0, np.zeros(6), w))
    times = np.arange(0.0, 6.0, 0.01)
    fluxes = _fluxes(scene, times)
    from ftsensord.processing.creep import CreepCompensation

    plain = _pipeline(series=HARSH)
    plain.creep = CreepCompensation(None, 100.0)  # the daemon as without the stage
    compensated = _pipeline(series=HARSH)
    raw = np.array([plain.step(_results(b)).wrench for b in fluxes])
    out = np.array([compensated.step(_results(b)).wrench for b in fluxes])
    after = times >= 1.5  # from 0.5 s after the step on
    creep = raw[after, 0] - raw[-1, 0]
    assert np.abs(creep).max() > 0.1  # the calibration's static estimate creeps by more than 5 % of the step
    # The compensated one stays within 2 % of its own final value (the packaged calibration's
    # static error on Fx is the same with or without it).
    assert np.abs(out[after, 0] - out[-1, 0]).max() < 0.04
    # A fault: a chip missing for a sample is flagged, and nothing of it enters the state: two
    # pipelines whose flagged samples differ (another chip missing) go on alike.
    twin = _pipeline(series=HARSH)
    for b in fluxes:
        twin.step(_results(b))
    a_flagged = compensated.step(_results(fluxes[-1], missing=3))
    b_flagged = twin.step(_results(fluxes[-1], missing=5))
    assert a_flagged.flags & wire.FLAG_DEGRADED and b_flagged.flags & wire.FLAG_DEGRADED
    assert not np.allclose(a_flagged.wrench, b_flagged.wrench, rtol=0, atol=1e-9)
    for b in fluxes[-5:]:
        assert np.array_equal(compensated.step(_results(b)).wrench, twin.step(_results(b)).wrench)
    # A fault longer than MAX_COAST_S: the state is dropped, the next clean sample starts afresh
    # (a load long held: the estimate itself, the scale being 1 here).
    assert compensated.creep.restarts == 0
    for _ in range(60):  # 0.6 s at 100 Hz
        assert compensated.step(_results(fluxes[-1], missing=3)).flags & wire.FLAG_DEGRADED
    assert compensated.creep.restarts == 1
    y = plain.step(_results(fluxes[-1])).wrench
    assert np.allclose(compensated.step(_results(fluxes[-1])).wrench, y, atol=1e-12)
    # A tare: the history of the old zero is dropped too.
    compensated.tare(fluxes[-1])
    assert compensated.creep.restarts == 2
    assert np.allclose(compensated.step(_results(fluxes[-1])).wrench, 0.0, atol=1e-9)
    assert sensor_status(compensated)["silicone"]["restarts"] == 2


def test_a_rate_change_restarts_the_stage_with_the_new_period():
    from ftsensord.calibration.relaxation import SiliconeCalibration
    from ftsensord.processing.creep import CreepCompensation

    stage = CreepCompensation(SiliconeCalibration(SERIES, 1.1, 0.0), 100.0)
    for _ in range(10):
        stage.apply(np.zeros(6), True)
    first_of_a_step = stage.apply(np.full(6, 1.1), True)
    assert first_of_a_step[0] > 1.0 + 1e-3  # the inverse reads the step's creep to come
    stage.configure(200.0)
    assert stage.apply(np.full(6, 1.1), True) == pytest.approx(
        np.ones(6)
    )  # afresh: held, divided by the scale
    assert stage.inverse.a[0, 0] == pytest.approx(np.exp(-0.005 / SERIES.creep[1][0]))


def test_the_hold_and_the_series_survive_their_files(tmp_path):
    from dataclasses import replace

    from ftsensord.calibration.calfile import Calibration
    from ftsensord.calibration.dataset import Dataset, Hold
    from ftsensord.calibration.relaxation import SiliconeCalibration

    cal = replace(_packaged_calibration(), silicone=SiliconeCalibration(SERIES, 1.05, 0.01))
    cal.save(tmp_path / "cal.json")
    assert Calibration.load(tmp_path / "cal.json").silicone == cal.silicone
    from ftsensord.calibration.procedure import simulate_dataset

    ds = simulate_dataset(
        _part_with_memory(SERIES),
        "sensor1",
        "six-axis",
        poses=12,
        validation_poses=2,
        samples=2,
        seed=0,
        sweeps=False,
        no_load_poses=0,
        hold_s=0.05,
    )
    assert ds.hold is not None and len(ds.hold.times_s) > 5
    ds.save(tmp_path / "ds.json")
    back = Dataset.load(tmp_path / "ds.json").hold
    assert (
        isinstance(back, Hold)
        and np.allclose(back.flux_t, ds.hold.flux_t)
        and np.allclose(back.loads, ds.hold.loads)
    )
    import json

    doc = json.loads((tmp_path / "ds.json").read_text())
    doc["hold"]["load_times_s"][0] = doc["hold"]["times_s"][0] + 1e-3  # a reading before any load
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    assert_names_file_and_key(
        Dataset.load, tmp_path / "bad.json", "times_s", "readings from the first load's time on"
    )
    doc = json.loads((tmp_path / "ds.json").read_text())
    doc["hold"]["load_times_s"][-1] = doc["hold"]["times_s"][-1] + 1.0  # a load no reading saw
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    assert_names_file_and_key(
        Dataset.load, tmp_path / "bad.json", "load_times_s", "loads applied before the last reading"
    )


def test_a_calibration_without_a_hold_says_so_and_the_daemon_runs_as_before():
    from ftsensord.calibration.procedure import calibrate
    from ftsensord.calibration.rig import record_dataset
    from ftsensord.config.sensors import SensorConfig
    from ftsensord.processing.filters import WrenchFilter
    from ftsensord.processing.pipeline import SensorPipeline
    from ftsensord.sim import VirtualClock, simulated_bus, two_sensor_scene
    from ftsensord.sim.loads import paper_plan

    scene = two_sensor_scene()
    bus = simulated_bus(scene, clock=VirtualClock(), seed=3)
    ds = record_dataset(
        bus,
        ADDRESSES,
        paper_plan("six-axis", n_fit=60, n_validation=10),
        lambda w: scene.set_load(0, StaticLoad(w)),
        samples=4,
        serial="sim-1",
    )
    cal, _ = calibrate(ds, nonlinear=False)
    assert cal.silicone is None and "no step-and-hold segment" in cal.report["silicone"]
    config = SensorConfig("sensor1", ADDRESSES, __import__("pathlib").Path("cal.json"), cal, "sensor")
    pipeline = SensorPipeline.build(config, WrenchFilter(), 2, thermal=False)
    assert pipeline.creep.inverse is None and sensor_status(pipeline)["silicone"] is None
    w = np.array([1.0, 2, 3, 0.1, 0.2, 0.3])
    assert pipeline.creep.apply(w, True) is w  # passed through as it is


def test_skipped_cycles_are_coasted_through_as_flagged_samples_not_a_restart():
    # A missed deadline (the loop skips its sample) must not throw minutes of creep away:
    # the state coasts as through a flagged sample, and is dropped only beyond MAX_COAST_S.
    from ftsensord.calibration.relaxation import SiliconeCalibration
    from ftsensord.daemon.loop import LoopTiming
    from ftsensord.processing.creep import MAX_COAST_S, CreepCompensation

    step = np.array([2.0, 0, 0, 0, 0, 0])
    skipped, flagged = (CreepCompensation(SiliconeCalibration(SERIES, 1.0, 0.0), 100.0) for _ in range(2))
    for stage in (skipped, flagged):
        for _ in range(300):  # 3 s into a held step: the slow term is still creeping
            stage.apply(step, True)
    skipped.gap(3)
    for _ in range(3):
        flagged.apply(step, False)
    assert skipped.restarts == flagged.restarts == 0
    assert np.array_equal(skipped.apply(step, True), flagged.apply(step, True))
    skipped.gap(round(MAX_COAST_S * 100) + 1)  # longer than the state may coast: dropped
    assert skipped.restarts == 1
    timing = LoopTiming()  # the loop's count of what a cycle skipped
    assert [timing.gap(s) for s in (0, 1, 5, 6, 2)] == [0, 0, 3, 0, -1]


def test_a_step_back_in_time_drops_the_state_and_a_skip_coasts_it():
    """`gap`: skipped cycles (positive) coast the state as flagged samples do; a loop whose
    time went back (negative, `LoopTiming.gap`) drops it: nothing of the past is known to
    be before now."""
    from ftsensord.calibration.relaxation import SiliconeCalibration
    from ftsensord.processing.creep import CreepCompensation

    stage = CreepCompensation(SiliconeCalibration(SERIES, 1.0, 0.0), 100.0)
    for _ in range(100):
        stage.apply(np.array([2.0, 0, 0, 0, 0, 0]), True)
    stage.gap(2)
    assert stage.restarts == 0 and stage.inverse is not None and stage.inverse.last is not None
    stage.gap(-1)
    assert stage.restarts == 1 and stage.inverse.last is None
