"""SE(3) helpers: round trips over the whole range, and a test at every branch point."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from ftsensord.model import se3

unit_vectors = (
    st.tuples(*[st.floats(-1, 1)] * 3)
    .map(np.array)
    .filter(lambda v: np.linalg.norm(v) > 1e-3)
    .map(lambda v: v / np.linalg.norm(v))
)


def rot_about(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues written out independently of se3, as the reference."""
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def test_hat_vee_and_cross_product():
    w, x = np.array([0.3, -1.2, 2.0]), np.array([1.0, 0.5, -0.7])
    assert np.allclose(se3.hat(w) @ x, np.cross(w, x))
    assert np.array_equal(se3.vee(se3.hat(w)), w)
    xi = np.array([1, 2, 3, 0.1, 0.2, 0.3])
    assert np.array_equal(se3.vee(se3.hat6(xi)), xi)
    ws = np.random.default_rng(0).normal(size=(5, 3))  # stacked: one matrix per row
    assert np.allclose(se3.hat(ws) @ x, np.cross(ws, x))


@given(unit_vectors, st.floats(0, np.pi))
def test_exp_so3_matches_rodrigues_and_is_a_rotation(axis, angle):
    R = se3.exp_so3(axis * angle)
    assert np.allclose(R, rot_about(axis, angle), atol=1e-14)
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-14) and np.linalg.det(R) == pytest.approx(1.0)


@given(unit_vectors, st.floats(0, np.pi - 1e-6))
def test_log_exp_round_trip_over_the_range(axis, angle):
    w = axis * angle
    assert np.allclose(se3.log_so3(se3.exp_so3(w)), w, atol=1e-10)


@given(unit_vectors, st.floats(np.pi - 1e-9, np.pi))
def test_log_near_pi_recovers_the_rotation(axis, angle):
    R = rot_about(axis, angle)
    w = se3.log_so3(R)
    assert np.linalg.norm(w) == pytest.approx(angle, abs=1e-9)
    assert np.allclose(se3.exp_so3(w), R, atol=1e-12)
    # The axis comes back up to sign (at pi both signs are the same rotation).
    assert abs(abs(float(w @ axis)) / np.linalg.norm(w) - 1.0) < 1e-9


@given(unit_vectors, st.floats(0, 1e-12))
def test_log_below_1e_12_is_exact_to_the_last_digits(axis, angle):
    w = axis * angle
    back = se3.log_so3(se3.exp_so3(w))
    assert np.allclose(back, w, rtol=1e-9, atol=1e-24)


@pytest.mark.parametrize("angle", [se3.SMALL_ANGLE * (1 - 1e-9), se3.SMALL_ANGLE * (1 + 1e-9)])
def test_both_sides_of_the_small_angle_branch_agree(angle):
    axis = np.array([0.48, -0.6, 0.64])
    w = axis * angle
    R = se3.exp_so3(w)
    assert np.allclose(R, rot_about(axis, angle), atol=1e-16)
    assert np.allclose(se3.log_so3(R), w, rtol=1e-12)
    xi = np.array([1e-3, -2e-3, 5e-4, *w])
    assert np.allclose(se3.log_se3(se3.exp_se3(xi)), xi, rtol=1e-10)


@pytest.mark.parametrize("delta", [se3.NEAR_PI * (1 - 1e-6), se3.NEAR_PI * (1 + 1e-6)])
def test_both_sides_of_the_near_pi_branch_agree(delta):
    axis = np.array([0.48, -0.6, 0.64])
    w = axis * (np.pi - delta)
    assert np.allclose(se3.log_so3(se3.exp_so3(w)), w, atol=1e-12)


def test_log_at_exactly_pi_and_identity():
    R = np.diag([1.0, -1.0, -1.0])  # pi about x
    assert np.allclose(se3.log_so3(R), [np.pi, 0, 0])
    assert np.array_equal(se3.log_so3(np.eye(3)), np.zeros(3))
    assert np.array_equal(se3.log_se3(np.eye(4)), np.zeros(6))


@settings(max_examples=200)
@given(
    unit_vectors,
    st.floats(0, np.pi - 1e-6),
    st.tuples(*[st.floats(-10, 10)] * 3).map(np.array),
    st.sampled_from([1e-12, 1e-6, 1.0, 1e3]),
)
def test_se3_round_trip_for_tiny_and_large_translations(axis, angle, v, scale):
    xi = np.concatenate([v * scale, axis * angle])
    T = se3.exp_se3(xi)
    assume(np.linalg.norm(xi[:3]) > 0)
    back = se3.log_se3(T)
    assert np.allclose(back[3:], xi[3:], atol=1e-10)
    assert np.allclose(back[:3], xi[:3], rtol=1e-8, atol=1e-9 * scale * 10)


@given(unit_vectors, st.floats(np.pi - 1e-9, np.pi), st.tuples(*[st.floats(-1, 1)] * 3).map(np.array))
def test_se3_log_near_pi_reproduces_the_pose(axis, angle, p):
    T = se3.pose(rot_about(axis, angle), p)
    assert np.allclose(se3.exp_se3(se3.log_se3(T)), T, atol=1e-9)


def test_left_jacobian_inverse_is_the_inverse_over_the_range():
    for angle in (0.0, 1e-8, se3.SMALL_ANGLE, 0.5, 2.0, np.pi - 1e-6, np.pi):
        w = np.array([0.6, 0.0, 0.8]) * angle
        assert np.allclose(se3.left_jacobian_inv_so3(w) @ se3.left_jacobian_so3(w), np.eye(3), atol=1e-12)


def test_adjoint_maps_twists_and_wrench_transform_preserves_power():
    rng = np.random.default_rng(3)
    T = se3.exp_se3(rng.normal(size=6))
    xi = rng.normal(size=6)
    # Ad_T xi is the twist seen in the other frame: T exp(xi) T^-1 = exp(Ad_T xi).
    assert np.allclose(se3.exp_se3(se3.adjoint(T) @ xi), T @ se3.exp_se3(xi) @ se3.inverse(T), atol=1e-10)
    # Power is frame independent: w_a . (Ad_T_ab xi_b) == w_b . xi_b with w_a = X_ab w_b.
    w_b = rng.normal(size=6)
    w_a = se3.wrench_transform(T) @ w_b
    assert float(w_a @ (se3.adjoint(T) @ xi)) == pytest.approx(float(w_b @ xi))


def test_wrench_transform_is_the_papers_tip_formula_for_parallel_frames():
    p = np.array([0.0, 0.01, -0.15])  # sensor 15 cm above the tip
    f, m = np.array([1.0, 2.0, -3.0]), np.array([0.01, 0.0, 0.02])
    w_tip = se3.wrench_transform(se3.pose(p=p)) @ np.concatenate([f, m])
    assert np.allclose(w_tip, np.concatenate([f, m + np.cross(p, f)]))


@pytest.mark.parametrize("angle", [1e110, 1e200, np.inf, np.nan])
def test_an_overflowing_or_non_finite_rotation_gives_nan_not_an_exception(angle):
    # The coefficients in math's floats: math.sin(inf) and 1e110 ** 3 raise where numpy's gave
    # inf or NaN; a rotation that large is no rotation, and its callers test for finite results.
    with np.errstate(all="ignore"):
        R = se3.exp_so3(np.array([angle, 0.0, 0.0]))
        T = se3.exp_se3(np.array([0.0, 0.0, 0.0, 0.0, angle, 0.0]))
    assert R.shape == (3, 3) and T.shape == (4, 4)
    assert not np.isfinite(R).all() or not np.isfinite(T).all() or np.allclose(R @ R.T, np.eye(3))


@pytest.mark.parametrize(
    "angle",
    [
        0.0,
        1e-9,
        5e-3,
        se3.SMALL_ANGLE * (1 - 1e-7),
        se3.SMALL_ANGLE,
        0.3,
        1.2,
        3.0,
        np.pi - 2 * se3.NEAR_PI,
        np.pi - se3.NEAR_PI * (1 + 1e-7),
        np.pi - se3.NEAR_PI,
        np.pi,
    ],
)
def test_the_se3_log_is_exps_inverse_on_each_side_of_its_branches(angle):
    """`log_se3` in floats switches to its series below `SMALL_ANGLE` and hands over to
    `log_so3`'s symmetric part within `NEAR_PI` of pi: on each side of both, it takes
    `exp_se3`'s pose back to its twist (the independent Rodrigues for the rotation)."""
    axis = np.array([0.3, -0.5, 0.81]) / np.linalg.norm([0.3, -0.5, 0.81])
    xi = np.concatenate([[2e-3, -1e-3, 4e-3], angle * axis])
    T = se3.exp_se3(xi)
    assert np.allclose(T[:3, :3], rot_about(axis, angle), rtol=0, atol=1e-15)
    assert np.allclose(se3.log_se3(T), xi, rtol=0, atol=1e-9 if angle == np.pi else 1e-12)
