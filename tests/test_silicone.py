"""The silicone's memory: the Prony series' creep, the scene's deflection under a held
load, and the recursive inverse that undoes it."""

from __future__ import annotations

import numpy as np
import pytest

from ftsensord.model import se3
from ftsensord.model.viscoelastic import CreepFilter, CreepInverse, Relaxation
from ftsensord.sim import load_scene
from ftsensord.sim.loads import RecordedLoad, StaticLoad, StepLoad
from ftsensord.sim.physics import PAPER_STIFFNESS_DIAG, PhysicalScene, SimSensor
from ftsensord.sim.silicone import DEFAULT_RELAXATION

from .conftest import assert_names_file_and_key

SERIES = Relaxation.from_pairs(DEFAULT_RELAXATION)
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


@pytest.mark.parametrize("relaxation, expected", [
    ("[[0.5, 1.0], [0.5, 2.0]]", "summing below 0.9"),
    ("[[0.1, -1.0]]", "times > 0"),
    ("[[0.1]]", "pairs [fraction, time_s]"),
    ("0.1", "pairs [fraction, time_s]"),
])
def test_a_bad_series_is_refused_naming_file_and_key(tmp_path, relaxation, expected):
    path = tmp_path / "scene.toml"
    path.write_text(f'version = 1\nkind = "sensors"\n[[sensor]]\naddresses = {list(ADDRESSES)}\n'
                    f'[sensor.silicone]\nrelaxation = {relaxation}\n')
    assert_names_file_and_key(load_scene, path, "relaxation", expected)


def test_a_scene_file_asks_for_the_memory_and_gets_the_default(tmp_path):
    path = tmp_path / "scene.toml"
    path.write_text(f'version = 1\nkind = "sensors"\n[[sensor]]\naddresses = {list(ADDRESSES)}\n'
                    f'[sensor.silicone]\n[[sensor]]\naddresses = {list(range(0x14, 0x1C))}\n')
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
