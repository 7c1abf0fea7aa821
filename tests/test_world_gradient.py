"""The stray stage (`processing.stray`, stray_field = "world"): a motor's gradient, fixed in the
world, learnt from the two parts the ring tells from a load as the tool turns, then the
three it cannot tell taken out of the flux."""

from __future__ import annotations

import numpy as np
import pytest

from ftsensord.calibration.calfile import Calibration
from ftsensord.chip import mlx90393 as mlx
from ftsensord.config.file import builtin_path, load_config
from ftsensord.model import se3
from ftsensord.model.geometry import SensorGeometry, gradient_basis
from ftsensord.processing.pipeline import channel_sigma_t
from ftsensord.processing.stray import (
    CORRECT_WITHIN,
    WorldGradient,
    parts,
    turned,
)
from ftsensord.protocol import wire
from ftsensord.sim import default_scene
from ftsensord.sim.loads import FixedOrientation
from ftsensord.sim.physics import StraySource

from .conftest import assert_names_file_and_key

SIGMA_T = channel_sigma_t(mlx.Settings(), 8)
#: Issue 23's figure: the median of each hold within 0.05 N and 2 mNm (RMS over holds).
TARGET = np.array([0.05, 0.05, 0.05, 2e-3, 2e-3, 2e-3])
#: Samples of a hold's start left out, as benchmarks/accuracy/motor.py leaves out its first 50 ms:
#: the turn's end (here also the motor's switching on, at the first hold).
SETTLE = 5


def random_gradient(rng: np.random.Generator) -> np.ndarray:
    A = rng.normal(size=(3, 3))
    G = A + A.T
    return G - np.trace(G) / 3 * np.eye(3)


def test_the_parts_of_a_turned_gradient_are_those_of_r_t_g_r():
    """T(R) against the tensor turned directly, at random and at the singular-looking turns
    (the identity, half turns about each axis: sign flips only, nothing lost)."""
    rng = np.random.default_rng(4)
    turns = (
        [np.eye(3)]
        + [se3.exp_so3(np.pi * e) for e in np.eye(3)]
        + [se3.exp_so3(rng.normal(size=3)) for _ in range(20)]
    )
    for R in turns:
        G = random_gradient(rng)
        assert np.allclose(turned(R) @ parts(G), parts(R.T @ G @ R), atol=1e-12)
        # A rotation of a traceless symmetric tensor keeps its norm: T(R) is invertible always.
        assert np.linalg.cond(turned(R)) < 10
    assert np.allclose(np.einsum("kij,k->ij", gradient_basis(), parts(G)), G)  # the parts rebuild G


def test_the_gradients_flux_is_each_chips_field_from_its_place():
    """F's columns: the field R_0i^T G p_i at each chip of the drawn ring; they span what
    `SensorGeometry.gradient_directions` does (one basis, two writings)."""
    ring, rng = SensorGeometry.ring(), np.random.default_rng(5)
    G = random_gradient(rng)
    expected = np.concatenate([R.T @ G @ p for R, p in zip(ring.chip_R, ring.chip_p, strict=True)])
    assert np.allclose(ring.gradient_flux() @ parts(G), expected, atol=1e-15)
    q, _ = np.linalg.qr(ring.gradient_flux())
    assert np.allclose(q @ (q.T @ ring.gradient_directions()), ring.gradient_directions(), atol=1e-12)


def _scene_with_motor(distance_m: float, seed: int):
    """The default scene (sensor1 as built, in the Earth's field) and a 2 A m^2 dipole fixed
    in the world at ``distance_m`` from its centre, direction and moment drawn from ``seed``."""
    rng = np.random.default_rng(seed)
    d, m = rng.normal(size=3), rng.normal(size=3)
    scene = default_scene()
    motor = StraySource(d / np.linalg.norm(d) * distance_m, m / np.linalg.norm(m) * 2.0)
    return scene, motor


def _flux(scene, cal, R: np.ndarray, rng: np.random.Generator | None) -> np.ndarray:
    scene.set_orientation(0, FixedOrientation(R))
    b = np.concatenate([scene.field_t(a, 0.0) for a in cal.addresses])
    return b if rng is None else b + rng.normal(size=b.size) * SIGMA_T


@pytest.mark.parametrize("on_at_tare", [False, True], ids=["on after tare", "tared on"])
@pytest.mark.parametrize("seed", [21, 22, 23])
def test_a_motor_is_learnt_as_the_tool_turns_and_taken_out(seed, on_at_tare):
    """Issue 23's scene at the flux: tared with the motor off and then switched on (2 A m^2,
    15 cm), or tared with it on; the tool held at 16 orientations for 50 noisy samples each.
    Uncorrected, the holds' medians are off beyond the figure (RMS over holds); with the
    stage, the medians of each hold's unflagged samples are within two thirds of it, and
    the gradient is learnt within the first few orientations (flagged until then; tared
    with the motor on, any change beyond noise: the first turn moved the hidden parts 30
    mNm's worth while the in-plane ones moved little)."""
    cal = Calibration.load(builtin_path("sim-sensor1.json"))
    scene, motor = _scene_with_motor(0.15, seed)
    rng = np.random.default_rng(seed)
    stage = WorldGradient(cal.model, SIGMA_T)
    turns = [se3.exp_so3(v) for v in np.random.default_rng(seed + 100).normal(size=(16, 3))]
    scene.stray_sources = [motor] if on_at_tare else []
    zero = np.mean([_flux(scene, cal, turns[0], rng) for _ in range(100)], axis=0)
    stage.turn_to(turns[0])
    stage.tared(zero)
    tared = cal.model.with_zero(zero)
    scene.stray_sources = [motor]
    raw, medians, learnt_at = [], [], None
    for k, R in enumerate(turns):
        hold_raw, hold = [], []
        for i in range(50):
            b = _flux(scene, cal, R, rng)
            stage.turn_to(R)
            fixed, flagged = stage.apply(b)
            hold_raw.append(tared.wrench(b))
            if not flagged and i >= SETTLE:
                hold.append(tared.wrench(fixed))
            stage.learn(b)
        learnt_at = k if learnt_at is None and stage.correcting else learnt_at
        raw.append(np.median(hold_raw, axis=0))
        if hold:
            medians.append(np.median(hold, axis=0))
    raw_rms = np.sqrt(np.mean(np.square(raw), axis=0))
    assert np.any(raw_rms > TARGET), raw_rms  # the scene is one the figure is about
    assert learnt_at is not None and learnt_at <= 6, learnt_at  # tared on: learning starts at the first turn
    assert len(medians) >= 10  # the holds once learnt (tared on: from the sixth at the latest)
    # Within the figure with a third to spare: what remains is the field's curvature across
    # the ring (the part no first-order gradient holds) and the estimate's noise, up to
    # CORRECT_WITHIN (a quarter of the figure); seen here: 0.5-1.2 mNm, 0.004-0.009 N.
    rms = np.sqrt(np.mean(np.square(medians), axis=0))
    assert np.all(rms < TARGET * 2 / 3), (rms, raw_rms)


def test_without_a_gradient_nothing_is_flagged_or_corrected_beyond_noise():
    """The motor off throughout, the tool turned: the learnt gradient is noise, and what it
    takes out is far below the correction's own tolerance."""
    cal = Calibration.load(builtin_path("sim-sensor1.json"))
    scene, rng = default_scene(), np.random.default_rng(9)
    stage = WorldGradient(cal.model, SIGMA_T)
    turns = [se3.exp_so3(v) for v in rng.normal(size=(12, 3))]
    zero = np.mean([_flux(scene, cal, turns[0], rng) for _ in range(100)], axis=0)
    stage.turn_to(turns[0])
    stage.tared(zero)
    flagged = 0
    for R in turns:
        for _ in range(40):
            b = _flux(scene, cal, R, rng)
            stage.turn_to(R)
            fixed, flag = stage.apply(b)
            flagged += flag
            if stage.correcting:
                assert np.all(np.abs(cal.model.KA @ (b - fixed)) < 3 * CORRECT_WITHIN)
            stage.learn(b)
    assert stage.correcting and flagged == 0


def test_world_needs_the_orientation_stream(tmp_path):
    (tmp_path / "c.toml").write_text(
        'version = 1\nbus = "sim"\n[[sensor]]\nname = "sensor1"\n'
        "addresses = [0x0C, 0x0D, 0x0E, 0x0F, 0x10, 0x11, 0x12, 0x13]\n"
        'calibration = "builtin:sim-sensor1.json"\nstray_field = "world"\n'
    )
    assert_names_file_and_key(
        load_config, tmp_path / "c.toml", "sensor[0].stray_field", 'orientation = "stream"'
    )
    assert wire.FLAG_INCONSISTENT  # the flag the stage uses before it has learnt
