"""SO(3) and SE(3): hat, vee, exp, log, adjoint, accurate at the extremes.

Conventions (the paper's, section IV): a twist is ``xi = [v; w]`` (translation
part first, m; rotation part second, rad), a wrench is ``[f; m]`` (N; Nm), and
a pose ``T`` is a 4x4 homogeneous matrix. ``T_ab`` is frame b seen from frame a.

Every branch threshold below carries its reason; tests sit at each one.
"""

from __future__ import annotations

import math

import numpy as np

#: Below this angle (rad) the coefficient functions use their Taylor series:
#: the closed forms divide differences of nearly equal numbers by theta^2 or
#: theta^3 and lose digits (about eps / theta^2), while the series truncated
#: after the theta^4 (or theta^6) term errs by less than 1e-18 here.
SMALL_ANGLE = 1e-2

#: Within this distance of pi (rad) `log_so3` reads the axis from the symmetric
#: part of R: the antisymmetric part is sin(theta) * axis, which beyond this
#: point is below 1e-3 and would cost more than three digits of the axis.
NEAR_PI = 1e-3


def hat(w: np.ndarray) -> np.ndarray:
    """The 3x3 skew matrix of ``w``: ``hat(w) @ x == cross(w, x)``; for ``w`` of
    shape (n, 3), the n matrices (n, 3, 3)."""
    w = np.asarray(w, dtype=float)
    m = np.zeros(w.shape[:-1] + (3, 3))
    m[..., 0, 1], m[..., 0, 2], m[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
    m[..., 1, 0], m[..., 2, 0], m[..., 2, 1] = w[..., 2], -w[..., 1], w[..., 0]
    return m


def vee(m: np.ndarray) -> np.ndarray:
    """Inverse of `hat` for 3x3; for a 4x4 se(3) matrix, the twist [v; w]."""
    if m.shape == (4, 4):
        return np.concatenate([m[:3, 3], vee(m[:3, :3])])
    return np.array([m[2, 1], m[0, 2], m[1, 0]])


def hat6(xi: np.ndarray) -> np.ndarray:
    """The 4x4 se(3) matrix of the twist ``xi = [v; w]``."""
    out = np.zeros((4, 4))
    out[:3, :3] = hat(xi[3:])
    out[:3, 3] = xi[:3]
    return out


def _coefficients(theta: float) -> tuple[float, float, float]:
    """A = sin(t)/t, B = (1 - cos t)/t^2, C = (t - sin t)/t^3."""
    if theta < SMALL_ANGLE:
        t2 = theta * theta
        return (1 - t2 / 6 + t2 * t2 / 120,
                0.5 - t2 / 24 + t2 * t2 / 720,
                1 / 6 - t2 / 120 + t2 * t2 / 5040)
    # math's, not numpy's: Python floats keep every product after them cheap (the
    # estimator's steps, `se3floats`, do a few dozen with these).
    if theta == math.inf:  # a twist that overflowed: NaN, as numpy's sin gave (math's raises)
        return math.nan, math.nan, math.nan
    s, c = math.sin(theta), math.cos(theta)
    t2 = theta * theta  # products, not **: a float's ** raises on overflow where * gives inf
    return s / theta, (1 - c) / t2, (theta - s) / (t2 * theta)


def exp_so3(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector ``w`` (rad), by Rodrigues."""
    w = np.asarray(w, dtype=float)
    a, b, _ = _coefficients(float(np.linalg.norm(w)))
    W = hat(w)
    return np.eye(3) + a * W + b * (W @ W)


def log_so3(R: np.ndarray) -> np.ndarray:
    """Rotation vector (rad) of the rotation matrix ``R``; angle in [0, pi].

    At exactly pi, w and -w are the same rotation; the one returned has the
    sign of the largest axis component positive.
    """
    s = 0.5 * vee(R - R.T)  # sin(theta) * axis
    c = 0.5 * (np.trace(R) - 1.0)  # cos(theta)
    sin_theta = float(np.linalg.norm(s))
    theta = float(np.arctan2(sin_theta, c))  # accurate at every angle, unlike arccos
    if theta < SMALL_ANGLE:
        t2 = theta * theta
        return (1 + t2 / 6 + 7 * t2 * t2 / 360) * s  # theta / sin(theta), as a series
    if np.pi - theta > NEAR_PI:
        return theta / sin_theta * s
    # Near pi: (R + R^T)/2 = cos(t) I + (1 - cos t) a a^T, well conditioned here.
    aat = (0.5 * (R + R.T) - c * np.eye(3)) / (1.0 - c)
    k = int(np.argmax(np.diag(aat)))
    axis = aat[:, k] / np.sqrt(aat[k, k])
    if sin_theta > 0 and float(axis @ s) < 0:
        axis = -axis  # the antisymmetric part still knows the sign below pi
    elif sin_theta == 0 and axis[np.argmax(np.abs(axis))] < 0:
        axis = -axis
    return theta * axis / np.linalg.norm(axis)


def left_jacobian_so3(w: np.ndarray) -> np.ndarray:
    """J_l(w) = I + B hat(w) + C hat(w)^2: maps v to the translation of exp([v; w])."""
    _, b, c = _coefficients(float(np.linalg.norm(w)))
    W = hat(w)
    return np.eye(3) + b * W + c * (W @ W)


def left_jacobian_inv_so3(w: np.ndarray) -> np.ndarray:
    """J_l(w)^-1 = I - hat(w)/2 + D hat(w)^2, D = 1/t^2 - cot(t/2)/(2t).

    D is finite on [0, pi] (1/12 at 0, 1/pi^2 at pi); the pole at 2 pi lies
    outside the range `log_so3` returns.
    """
    theta = float(np.linalg.norm(w))
    if theta < SMALL_ANGLE:
        t2 = theta * theta
        d = 1 / 12 + t2 / 720 + t2 * t2 / 30240  # the two terms of D cancel here
    else:
        d = 1 / theta**2 - 1 / (2 * theta * np.tan(theta / 2))
    W = hat(w)
    return np.eye(3) - 0.5 * W + d * (W @ W)


def exp_se3(xi: np.ndarray) -> np.ndarray:
    """The pose exp(hat6(xi)) of the twist ``xi = [v; w]`` (m, rad)."""
    xi = np.asarray(xi, dtype=float)
    T = np.eye(4)
    T[:3, :3] = exp_so3(xi[3:])
    T[:3, 3] = left_jacobian_so3(xi[3:]) @ xi[:3]
    return T


def log_se3(T: np.ndarray) -> np.ndarray:
    """The twist ``[v; w]`` with exp_se3(twist) == T; rotation angle in [0, pi]."""
    w = log_so3(T[:3, :3])
    return np.concatenate([left_jacobian_inv_so3(w) @ T[:3, 3], w])


def pose(R: np.ndarray | None = None, p: np.ndarray | None = None) -> np.ndarray:
    """The 4x4 pose of rotation ``R`` and position ``p`` (m)."""
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    if p is not None:
        T[:3, 3] = p
    return T


def inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of a pose, using R^T rather than a general matrix inverse."""
    R, p = T[:3, :3], T[:3, 3]
    return pose(R.T, -R.T @ p)


def adjoint(T: np.ndarray) -> np.ndarray:
    """Ad_T for twists [v; w]: [[R, hat(p) R], [0, R]]."""
    R, p = T[:3, :3], T[:3, 3]
    out = np.zeros((6, 6))
    out[:3, :3] = R
    out[:3, 3:] = hat(p) @ R
    out[3:, 3:] = R
    return out


def wrench_transform(T_ab: np.ndarray) -> np.ndarray:
    """Matrix that moves a wrench [f; m] from frame b to frame a.

    f_a = R f_b, m_a = R m_b + p x (R f_b), with T_ab = (R, p); equal to
    Ad(T_ba)^T. For parallel frames it is the paper's [[I, 0], [hat(p), I]].
    """
    R, p = T_ab[:3, :3], T_ab[:3, 3]
    out = np.zeros((6, 6))
    out[:3, :3] = R
    out[3:, :3] = hat(p) @ R
    out[3:, 3:] = R
    return out
