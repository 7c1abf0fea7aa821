"""SE(3)'s exp and log in Python floats, for the nonlinear estimator's steps: the same
formulas as `se3` (Rodrigues, the left Jacobian, the same series near zero), without a
dozen numpy calls on 3-vectors for every step of every sample."""

from __future__ import annotations

import math

import numpy as np

from . import se3


def exp_se3(xi: np.ndarray) -> np.ndarray:
    """`se3.exp_se3` of ``xi[:6]`` in Python floats: the same formulas (Rodrigues, the left
    Jacobian, the same series near zero), without a dozen numpy calls on 3-vectors every step."""
    v0, v1, v2, w0, w1, w2 = xi.tolist()[:6]
    ww = w0 * w0 + w1 * w1 + w2 * w2
    a, b, c = se3._coefficients(math.sqrt(ww))
    # R = I + a W + b W^2 and t = (I + b W + c W^2) v, W = hat(w), W^2 = w w^T - |w|^2 I.
    bw0, bw1, bw2, aw0, aw1, aw2 = b * w0, b * w1, b * w2, a * w0, a * w1, a * w2
    wv = w0 * v0 + w1 * v1 + w2 * v2
    x0, x1, x2 = w1 * v2 - w2 * v1, w2 * v0 - w0 * v2, w0 * v1 - w1 * v0  # W v
    return np.array([1.0 + bw0 * w0 - b * ww, bw0 * w1 - aw2, bw0 * w2 + aw1, v0 + b * x0 + c * (w0 * wv - ww * v0),
                     bw1 * w0 + aw2, 1.0 + bw1 * w1 - b * ww, bw1 * w2 - aw0, v1 + b * x1 + c * (w1 * wv - ww * v1),
                     bw2 * w0 - aw1, bw2 * w1 + aw0, 1.0 + bw2 * w2 - b * ww, v2 + b * x2 + c * (w2 * wv - ww * v2),
                     0.0, 0.0, 0.0, 1.0]).reshape(4, 4)


def log_se3(T: np.ndarray) -> np.ndarray:
    """`se3.log_se3` in Python floats, for turns short of pi (a deflection's, or a twin's);
    within `se3.NEAR_PI` of pi, where the axis needs the symmetric part, it is the one."""
    (r00, r01, r02, t0), (r10, r11, r12, t1), (r20, r21, r22, t2), _ = T.tolist()
    s0, s1, s2 = 0.5 * (r21 - r12), 0.5 * (r02 - r20), 0.5 * (r10 - r01)  # sin(theta) axis
    sin_theta = math.sqrt(s0 * s0 + s1 * s1 + s2 * s2)
    theta = math.atan2(sin_theta, 0.5 * (r00 + r11 + r22 - 1.0))
    if math.pi - theta <= se3.NEAR_PI:
        return se3.log_se3(T)
    tt = theta * theta
    if theta < se3.SMALL_ANGLE:  # theta / sin(theta) and D as series (se3's own)
        k, d = 1 + tt / 6 + 7 * tt * tt / 360, 1 / 12 + tt / 720 + tt * tt / 30240
    else:
        k, d = theta / sin_theta, 1 / tt - 1 / (2 * theta * math.tan(theta / 2))
    w0, w1, w2 = k * s0, k * s1, k * s2
    # J_l(w)^-1 t = t - (w x t) / 2 + D w x (w x t).
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
    D = np.array([r00, r01, r02, t0 - (r00 * s0 + r01 * s1 + r02 * s2),
                  r10, r11, r12, t1 - (r10 * s0 + r11 * s1 + r12 * s2),
                  r20, r21, r22, t2 - (r20 * s0 + r21 * s1 + r22 * s2),
                  0.0, 0.0, 0.0, 1.0]).reshape(4, 4)
    step = log_se3(D)
    v0, v1, v2, w0, w1, w2 = step.tolist()
    return exp_se3(step) @ pose, math.sqrt(v0 * v0 + v1 * v1 + v2 * v2), math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
