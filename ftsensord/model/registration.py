"""Point-set registration by SVD (Arun et al. 1987), in its reflection-safe form.

The 8 magnets of one sensor lie close to one plane: there the plain
``R = V U^T`` of the paper can be a reflection (det -1). Kabsch/Umeyama's
``R = V diag(1, 1, det(V U^T)) U^T`` is the nearest rotation instead.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Rank test on the centred point set: a singular value of H below this
#: fraction of the largest is noise. Points measured to about 1 um on a ring of
#: about 1 cm spread their H singular values by at most 1e-4 when collinear; 1e-6
#: sits between that and double-precision round-off (about 1e-16 relative).
RANK_TOL = 1e-6


@dataclass(frozen=True)
class Registration:
    """Result of `register`: the rotation R and translation t with Q ~ R P + t.

    ``rank`` is that of the centred cross-covariance H (3: a solid point set,
    2: coplanar, which still fixes the rotation, 1 or 0: collinear or a single
    point, where the rotation about the line is not determined and R is only
    one of many). ``rms`` is the residual in the points' unit.
    """

    R: np.ndarray
    t: np.ndarray
    rank: int
    rms: float

    @property
    def determined(self) -> bool:
        return self.rank >= 2

    def as_pose(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = self.R, self.t
        return T


def register(P: np.ndarray, Q: np.ndarray, weights: np.ndarray | None = None) -> Registration:
    """The rigid motion (R, t) minimising sum w_i |Q_i - (R P_i + t)|^2.

    ``P`` and ``Q`` are n x 3 (n >= 1) corresponding points; ``weights`` (n,)
    are non-negative (e.g. 0 for a chip that is missing). det(R) is +1 always.
    """
    P, Q = np.asarray(P, dtype=float), np.asarray(Q, dtype=float)
    if P.shape != Q.shape or P.ndim != 2 or P.shape[1] != 3 or len(P) == 0:
        raise ValueError(f"register needs two n x 3 arrays of the same shape, got {P.shape} and {Q.shape}")
    w = np.ones(len(P)) if weights is None else np.asarray(weights, dtype=float)
    if w.shape != (len(P),) or np.any(w < 0) or w.sum() <= 0:
        raise ValueError("weights must be n non-negative numbers, not all zero")
    w = w / w.sum()
    p_bar, q_bar = w @ P, w @ Q
    H = (P - p_bar).T @ ((Q - q_bar) * w[:, None])
    U, S, Vt = np.linalg.svd(H)
    d = 1.0 if np.linalg.det(Vt.T @ U.T) >= 0 else -1.0
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    t = q_bar - R @ p_bar
    rank = int(np.sum(S > RANK_TOL * S[0])) if S[0] > 0 else 0
    residual = Q - (P @ R.T + t)
    return Registration(R, t, rank, float(np.sqrt(w @ np.sum(residual**2, axis=1))))
