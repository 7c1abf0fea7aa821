"""Registration never returns a reflection: coplanar, nearly collinear, noisy sets."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ftsensord.model import se3
from ftsensord.model.registration import register

twists = st.tuples(*[st.floats(-0.01, 0.01)] * 3, *[st.floats(-np.pi + 1e-3, np.pi - 1e-3)] * 3).map(np.array)


def ring(n: int = 8, radius: float = 0.0134, z: float = 0.0025) -> np.ndarray:
    phi = 2 * np.pi * np.arange(n) / n
    return np.stack([radius * np.cos(phi), radius * np.sin(phi), np.full(n, z)], axis=1)


def moved(T: np.ndarray, P: np.ndarray) -> np.ndarray:
    return P @ T[:3, :3].T + T[:3, 3]


@given(twists)
def test_coplanar_ring_recovers_the_exact_pose(xi):
    P = ring()
    T = se3.exp_se3(xi)
    reg = register(P, moved(T, P))
    assert np.linalg.det(reg.R) == pytest.approx(1.0)
    assert np.allclose(reg.as_pose(), T, atol=1e-12)
    assert reg.rank == 2 and reg.determined and reg.rms < 1e-12


def test_the_plain_arun_solution_reflects_on_a_coplanar_set_where_this_does_not():
    # With coplanar points H has a zero singular value whose vectors' signs are
    # arbitrary: the paper's R = V U^T then comes out a reflection for some poses.
    rng = np.random.default_rng(7)
    P = ring()
    plain_reflections = 0
    for _ in range(100):
        Q = moved(se3.exp_se3(rng.normal(size=6)), P)
        H = (P - P.mean(0)).T @ (Q - Q.mean(0))
        U, _, Vt = np.linalg.svd(H)
        plain_reflections += np.linalg.det(Vt.T @ U.T) < 0
        assert np.linalg.det(register(P, Q).R) == pytest.approx(1.0)
    assert plain_reflections > 0


@settings(max_examples=200)
@given(twists, st.floats(0, 1e-5), st.integers(0, 2**32 - 1))
def test_noisy_points_give_a_rotation_close_to_the_truth(xi, noise, seed):
    rng = np.random.default_rng(seed)
    P = ring()
    T = se3.exp_se3(xi)
    reg = register(P, moved(T, P) + rng.normal(0, noise, P.shape))
    assert np.linalg.det(reg.R) == pytest.approx(1.0)
    assert np.allclose(reg.R @ reg.R.T, np.eye(3), atol=1e-12)
    # Angle error ~ noise / radius; 10 sigma of margin.
    angle_err = np.linalg.norm(se3.log_so3(reg.R.T @ T[:3, :3]))
    assert angle_err <= 10 * noise / 0.0134 + 1e-12


@given(st.floats(1e-12, 1e-6), st.integers(0, 2**32 - 1))
def test_nearly_collinear_points_still_give_a_proper_rotation(spread, seed):
    rng = np.random.default_rng(seed)
    x = np.linspace(-0.01, 0.01, 8)
    P = np.stack([x, spread * rng.normal(size=8), spread * rng.normal(size=8)], axis=1)
    Q = moved(se3.exp_se3(rng.normal(size=6)), P) + rng.normal(0, 1e-9, P.shape)
    reg = register(P, Q)
    assert np.linalg.det(reg.R) == pytest.approx(1.0)
    assert reg.rank <= 2


def test_exactly_collinear_and_single_points_are_reported_undetermined():
    P = np.stack([np.linspace(0, 1, 5), np.zeros(5), np.zeros(5)], axis=1)
    assert register(P, P + 1.0).rank == 1 and not register(P, P).determined
    one = register(P[:1], P[:1] + 2.0)
    assert one.rank == 0 and np.allclose(one.t, 2.0)


def test_zero_weight_drops_a_point():
    P = ring()
    T = se3.exp_se3(np.array([1e-3, 0, 0, 0, 0.05, 0]))
    Q = moved(T, P)
    Q[3] += 1.0  # a wildly wrong measurement
    reg = register(P, Q, weights=np.array([1, 1, 1, 0, 1, 1, 1, 1.0]))
    assert np.allclose(reg.as_pose(), T, atol=1e-12)


@pytest.mark.parametrize(
    ("P", "Q", "w"),
    [
        (np.zeros((3, 2)), np.zeros((3, 2)), None),
        (np.zeros((3, 3)), np.zeros((4, 3)), None),
        (np.zeros((0, 3)), np.zeros((0, 3)), None),
        (np.zeros((2, 3)), np.zeros((2, 3)), np.zeros(2)),
        (np.zeros((2, 3)), np.zeros((2, 3)), np.array([1.0, -1.0])),
    ],
)
def test_bad_input_is_refused(P, Q, w):
    with pytest.raises(ValueError):
        register(P, Q, w)
