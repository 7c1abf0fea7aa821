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
        return (1 - t2 / 6 + t2 * t2 / 120, 0.5 - t2 / 24 + t2 * t2 / 720, 1 / 6 - t2 / 120 + t2 * t2 / 5040)
    # math's, not numpy's: Python floats keep every product after them cheap (`exp_se3`).
    if theta == math.inf:  # a twist that overflowed: NaN, as numpy's sin gave (math's raises)
        return math.nan, math.nan, math.nan
    s, c = math.sin(theta), math.cos(theta)
    t2 = theta * theta  # products, not **: a float's ** raises on overflow where * gives inf
    return s / theta, (1 - c) / t2, (theta - s) / (t2 * theta)


def _log_factor(theta: float, sin_theta: float) -> float:
    """theta / sin(theta): the rotation vector from sin(theta) times its axis (away from pi)."""
    if theta < SMALL_ANGLE:
        t2 = theta * theta
        return 1 + t2 / 6 + 7 * t2 * t2 / 360  # the series: the ratio of two vanishing numbers
    return theta / sin_theta


def _jl_inv_d(theta: float) -> float:
    """D = 1/t^2 - cot(t/2)/(2t) of J_l^-1 = I - hat(w)/2 + D hat(w)^2: finite on [0, pi]
    (1/12 at 0, 1/pi^2 at pi); the pole at 2 pi lies outside the range `log_so3` returns."""
    if theta < SMALL_ANGLE:
        t2 = theta * theta
        return 1 / 12 + t2 / 720 + t2 * t2 / 30240  # the two terms of D cancel here
    return 1 / (theta * theta) - 1 / (2 * theta * math.tan(theta / 2))


def exp_se3(xi: np.ndarray) -> np.ndarray:
    """The pose exp(hat6(xi)) of the twist ``xi = [v; w]`` (m, rad): R by Rodrigues,
    R = I + A W + B W^2, and t = J_l(w) v = (I + B W + C W^2) v (`left_jacobian_so3`), with
    W = hat(w) and W^2 = w w^T - |w|^2 I, written out in Python floats: the nonlinear
    estimator takes a few per sample, and a dozen numpy calls on 3-vectors cost more than
    the arithmetic."""
    v0, v1, v2, w0, w1, w2 = np.asarray(xi, dtype=float).tolist()[:6]
    ww = w0 * w0 + w1 * w1 + w2 * w2
    a, b, c = _coefficients(math.sqrt(ww))
    bw0, bw1, bw2, aw0, aw1, aw2 = b * w0, b * w1, b * w2, a * w0, a * w1, a * w2
    wv = w0 * v0 + w1 * v1 + w2 * v2
    x0, x1, x2 = w1 * v2 - w2 * v1, w2 * v0 - w0 * v2, w0 * v1 - w1 * v0  # W v
    return np.array(
        [
            1.0 + bw0 * w0 - b * ww,
            bw0 * w1 - aw2,
            bw0 * w2 + aw1,
            v0 + b * x0 + c * (w0 * wv - ww * v0),
            bw1 * w0 + aw2,
            1.0 + bw1 * w1 - b * ww,
            bw1 * w2 - aw0,
            v1 + b * x1 + c * (w1 * wv - ww * v1),
            bw2 * w0 - aw1,
            bw2 * w1 + aw0,
            1.0 + bw2 * w2 - b * ww,
            v2 + b * x2 + c * (w2 * wv - ww * v2),
            0.0,
            0.0,
            0.0,
            1.0,
        ]
    ).reshape(4, 4)


def exp_so3(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector ``w`` (rad): `exp_se3`'s rotation."""
    w0, w1, w2 = np.asarray(w, dtype=float).tolist()
    return exp_se3(np.array([0.0, 0.0, 0.0, w0, w1, w2]))[:3, :3].copy()


def log_so3(R: np.ndarray) -> np.ndarray:
    """Rotation vector (rad) of the rotation matrix ``R``; angle in [0, pi].

    At exactly pi, w and -w are the same rotation; the one returned has the
    sign of the largest axis component positive.
    """
    s = 0.5 * vee(R - R.T)  # sin(theta) * axis
    c = 0.5 * (np.trace(R) - 1.0)  # cos(theta)
    sin_theta = float(np.linalg.norm(s))
    theta = float(np.arctan2(sin_theta, c))  # accurate at every angle, unlike arccos
    if np.pi - theta > NEAR_PI:
        return _log_factor(theta, sin_theta) * s
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
    """J_l(w)^-1 = I - hat(w)/2 + D hat(w)^2 (`_jl_inv_d`)."""
    W = hat(w)
    return np.eye(3) - 0.5 * W + _jl_inv_d(float(np.linalg.norm(w))) * (W @ W)


def log_se3(T: np.ndarray) -> np.ndarray:
    """The twist ``[v; w]`` with exp_se3(twist) == T; rotation angle in [0, pi]. Short of
    pi (a deflection's turn, or any step's) in Python floats, as `exp_se3`: w from sin(theta)
    times the axis, v = J_l(w)^-1 t = t - (w x t)/2 + D w x (w x t); within `NEAR_PI` of pi,
    where the axis needs R's symmetric part, by `log_so3`."""
    (r00, r01, r02, t0), (r10, r11, r12, t1), (r20, r21, r22, t2), _ = np.asarray(T, dtype=float).tolist()
    s0, s1, s2 = 0.5 * (r21 - r12), 0.5 * (r02 - r20), 0.5 * (r10 - r01)  # sin(theta) axis
    sin_theta = math.sqrt(s0 * s0 + s1 * s1 + s2 * s2)
    theta = math.atan2(sin_theta, 0.5 * (r00 + r11 + r22 - 1.0))
    if math.pi - theta <= NEAR_PI:
        w = log_so3(T[:3, :3])
        return np.concatenate([left_jacobian_inv_so3(w) @ T[:3, 3], w])
    k, d = _log_factor(theta, sin_theta), _jl_inv_d(theta)
    w0, w1, w2 = k * s0, k * s1, k * s2
    c0, c1, c2 = w1 * t2 - w2 * t1, w2 * t0 - w0 * t2, w0 * t1 - w1 * t0
    cc0, cc1, cc2 = w1 * c2 - w2 * c1, w2 * c0 - w0 * c2, w0 * c1 - w1 * c0
    return np.array([t0 - 0.5 * c0 + d * cc0, t1 - 0.5 * c1 + d * cc1, t2 - 0.5 * c2 + d * cc2, w0, w1, w2])


def continued(before: np.ndarray, pose: np.ndarray) -> tuple[np.ndarray, float, float]:
    """``pose`` moved on by the motion from ``before`` to it, T_k (T_k-1)^-1 T_k (constant
    velocity, left-multiplied as the estimator's steps), with that motion's size: its
    twist's translation (m) and turn (rad). Taken as a twist by `exp_se3`, so the result is
    a rigid motion to round-off (R_k R_k-1^T R_k as matrix products would compound theirs)."""
    # D = pose before^-1: R_D = R R_0^T, t_D = t - R_D t_0, in floats (a dozen numpy calls on
    # 3x3 blocks cost more than the arithmetic).
    (a0, a1, a2, s0), (b0, b1, b2, s1), (c0, c1, c2, s2), _ = before.tolist()
    (d0, d1, d2, t0), (e0, e1, e2, t1), (f0, f1, f2, t2), _ = pose.tolist()
    r00, r01, r02 = d0 * a0 + d1 * a1 + d2 * a2, d0 * b0 + d1 * b1 + d2 * b2, d0 * c0 + d1 * c1 + d2 * c2
    r10, r11, r12 = e0 * a0 + e1 * a1 + e2 * a2, e0 * b0 + e1 * b1 + e2 * b2, e0 * c0 + e1 * c1 + e2 * c2
    r20, r21, r22 = f0 * a0 + f1 * a1 + f2 * a2, f0 * b0 + f1 * b1 + f2 * b2, f0 * c0 + f1 * c1 + f2 * c2
    D = np.array(
        [
            r00,
            r01,
            r02,
            t0 - (r00 * s0 + r01 * s1 + r02 * s2),
            r10,
            r11,
            r12,
            t1 - (r10 * s0 + r11 * s1 + r12 * s2),
            r20,
            r21,
            r22,
            t2 - (r20 * s0 + r21 * s1 + r22 * s2),
            0.0,
            0.0,
            0.0,
            1.0,
        ]
    ).reshape(4, 4)
    step = log_se3(D)
    v0, v1, v2, w0, w1, w2 = step.tolist()
    return (
        exp_se3(step) @ pose,
        math.sqrt(v0 * v0 + v1 * v1 + v2 * v2),
        math.sqrt(w0 * w0 + w1 * w1 + w2 * w2),
    )


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
