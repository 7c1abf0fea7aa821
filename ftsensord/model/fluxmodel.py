"""The nonlinear estimator's forward model: the flux each chip reads for a centre-piece
pose and a uniform background field, and its derivative (`FluxModel`).

Each magnet a point dipole (moment along its axis), each chip's own magnet with its
octupole too (its cylinder shape: `ftsensord.model.magnet.octupole_field`), the chips
where the pose T puts them, each chip's reading through its response matrix and offset
(the free parameters a calibration fits). Units SI: T, m, A m^2; poses and fields in {0}.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import se3
from .geometry import SensorGeometry
from .magnet import MU0_OVER_4PI, octupole_field, octupole_ratio

_EYE3 = np.eye(3)


def dipole_pairs(r: np.ndarray, m: np.ndarray, gradient: bool = True
                 ) -> tuple[np.ndarray, np.ndarray | None]:
    """Field (..., 3) and its gradient dB/dr (..., 3, 3; None unless asked) of point
    dipoles of moment ``m`` (A m^2) at offsets ``r`` (m) from them, T and T/m, per pair:
    the sums over magnets are the caller's (the calibration needs them one by one)."""
    B, parts = _dipole_field(r, m)
    return B, (_dipole_gradient(r, m, *parts) if gradient else None)


def _dipole_field(r: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
    """`dipole_pairs`'s field, and what its gradient reuses (d^2, r.m, k / d^5)."""
    # As few numpy operations as the formulas allow: at 8 x 8 pairs each costs more in
    # call overhead than in arithmetic, and the estimator runs this twice an iteration.
    d2 = np.einsum("...i,...i->...", r, r)[..., None]
    rm = np.einsum("...i,...i->...", r, m)[..., None]
    k_d5 = MU0_OVER_4PI / (d2 * d2 * np.sqrt(d2))
    return k_d5 * (3 * rm * r - d2 * m), (d2, rm, k_d5)


def _dipole_gradient(r: np.ndarray, m: np.ndarray, d2: np.ndarray, rm: np.ndarray, k_d5: np.ndarray) -> np.ndarray:
    """dB/dr of a dipole: k (3 (m r^T + r m^T + (r.m) I) / d^5 - 15 (r.m) r r^T / d^7)."""
    mr = m[..., :, None] * r[..., None, :]
    outer = mr + np.swapaxes(mr, -1, -2) + rm[..., None] * _EYE3
    return k_d5[..., None] * (3 * outer - (15 * rm / d2)[..., None] * (r[..., :, None] * r[..., None, :]))


@dataclass
class FluxModel:
    """Predicted flux (T, chip frames) for a centre-piece pose and a background field.

    Chip i reads ``S_i R_i^T (B(p_i) + u) + o_i``: B the magnets' field (each a point
    dipole at ``geometry.magnet_p``, moment ``moment_am2`` times ``geometry.strengths``,
    along its axis, plus, with ``octupole``, each chip's own magnet's next multipole term
    for its cylinder shape (`ftsensord.model.magnet.octupole_field`; the others are 6 mm
    and more away, where it is 1e-4 of theirs); every other magnet's field too with
    ``crosstalk``), R_i and p_i the
    chip's rotation and position (moved by the pose), u a uniform background field in
    {0} (the room's; T). ``scale`` is S: per axis (n, 3) or a full response matrix per
    chip (n, 3, 3), which also absorbs a chip's tilt on the part; ``offset_t`` (n, 3) is o.
    """

    geometry: SensorGeometry
    moment_am2: float
    scale: np.ndarray = field(default_factory=lambda: np.ones((8, 3)))
    offset_t: np.ndarray = field(default_factory=lambda: np.zeros((8, 3)))
    crosstalk: bool = True
    octupole: bool = True

    @property
    def response(self) -> np.ndarray:
        """S as a matrix per chip (n, 3, 3); kept while ``scale`` is the same array."""
        cached = self.__dict__.get("_response")
        if cached is not None and cached[0] is self.scale and np.array_equal(cached[1], self.scale):
            return cached[2]  # the same scale, not changed in place since
        s = np.asarray(self.scale, dtype=float)
        response = s if s.ndim == 3 else s[:, :, None] * np.eye(3)
        self.__dict__["_response"] = (self.scale, s.copy(), response)
        return response

    @property
    def _response_chip(self) -> np.ndarray:
        """S R_chip^T (n, 3, 3), fixed while S and the geometry are: a pose's S R^T is
        this times R_T^T, one product where two were."""
        response = self.response
        cached = self.__dict__.get("_response_chip_cache")
        if cached is not None and cached[0] is response and cached[1] is self.geometry.chip_R:
            return cached[2]
        value = response @ np.transpose(self.geometry.chip_R, (0, 2, 1))
        self.__dict__["_response_chip_cache"] = (response, self.geometry.chip_R, value)
        return value

    def _fields(self, T: np.ndarray, gradient: bool = True) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        """World field B (n, 3), its gradient G (n, 3, 3; None unless asked), chip positions p."""
        # The estimator asks the field at a pose (is the step better?) and then, at the
        # same pose, its gradient too: the field's part is kept for that second call.
        last = self.__dict__.get("_last_field")
        moments = self._moments
        if last is not None and last[0] is T and last[2] is moments and np.array_equal(last[1], T):
            _, _, _, B_sum, p, r, m, parts = last
        else:
            g, (m, q) = self.geometry, moments
            p = g.chip_p @ T[:3, :3].T + T[:3, 3]
            r = p[:, None, :] - g.magnet_p[None, :, :]  # (chip, magnet, 3)
            if not self.crosstalk:
                own = np.arange(g.n_chips)
                r, m = r[own, own][:, None, :], m[0][own][:, None, :]
            B, dipole = _dipole_field(r, m)  # m broadcasts over the chips
            B_sum = B.sum(axis=1)
            own = None
            if self.octupole:
                own = (p - g.magnet_p, g.magnet_axis, q)
                B_sum = B_sum + octupole_field(*own, gradient=False)[0]
            parts = (dipole, own)
            self.__dict__["_last_field"] = (T, T.copy(), moments, B_sum, p, r, m, parts)
        G = None
        if gradient:
            G = _dipole_gradient(r, m, *parts[0]).sum(axis=1)
            if parts[1] is not None:
                G = G + octupole_field(*parts[1])[1]
        return B_sum, G, p

    @property
    def _moments(self) -> tuple[np.ndarray, np.ndarray]:
        """Each magnet's dipole moment (1, n, 3; A m^2) and octupole strength (n,; T m^5),
        kept while what they depend on is unchanged (a new array when it changes)."""
        g = self.geometry
        key = (self.moment_am2, self.crosstalk, self.octupole, id(g), g.strengths.tobytes())
        cached = self.__dict__.get("_moments_cache")
        if cached is None or cached[0] != key:
            m = (self.moment_am2 * g.strengths[:, None] * g.magnet_axis)[None, :, :]
            q = MU0_OVER_4PI * self.moment_am2 * g.strengths * octupole_ratio(g.magnet_radius_m, g.magnet_length_m)
            cached = (key, (m, q))
            self.__dict__["_moments_cache"] = cached
        return cached[1]

    def raw(self, T: np.ndarray) -> np.ndarray:
        """The magnets' field at each chip (n, 3), T, chip frames: before scale and offset."""
        B, _, _ = self._fields(T, gradient=False)
        R = np.einsum("ij,njk->nik", T[:3, :3], self.geometry.chip_R)
        return np.einsum("nji,nj->ni", R, B)

    def predict(self, T: np.ndarray, u: np.ndarray | None = None) -> np.ndarray:
        """Stacked flux (3n,), T, each chip in its own frame; ``u`` the background field
        in {0} (T; default none)."""
        B, _, _ = self._fields(T, gradient=False)
        if u is not None:
            B = B + u
        SRt = self._response_chip @ T[:3, :3].T  # S R^T, R = R_T R_chip
        return (np.einsum("nij,nj->ni", SRt, B) + self.offset_t).ravel()

    def predict_and_jacobian(self, T: np.ndarray, u: np.ndarray | None = None,
                             background: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Flux (3n,) and its derivative (3n, 6) for T <- exp([v; w]) T at v = w = 0;
        with ``background``, (3n, 9): the last 3 columns d/du, u the background field.

        The chip at p in rotation R reads b = S R^T (B(p) + u); perturbed, p moves by
        v + w x p and R turns by w, so db/dv = S R^T G, db/dw = S R^T (hat(B + u) - G hat(p))
        and db/du = S R^T.
        """
        B, G, p = self._fields(T)
        assert G is not None
        if u is not None:
            B = B + u
        SRt = self._response_chip @ T[:3, :3].T  # S R^T, R = R_T R_chip
        J_v = SRt @ G
        J_w = SRt @ (se3.hat(B) - G @ se3.hat(p))
        blocks = [J_v, J_w, SRt] if background else [J_v, J_w]
        J = np.concatenate(blocks, axis=2)
        b = np.einsum("nij,nj->ni", SRt, B) + self.offset_t
        return b.ravel(), J.reshape(-1, J.shape[2])

    def background_directions(self, T: np.ndarray | None = None) -> np.ndarray:
        """U (3n, 3): the flux a unit background field along x, y, z of {0} adds (T/T)."""
        R = self.geometry.chip_R if T is None else np.einsum("ij,njk->nik", T[:3, :3], self.geometry.chip_R)
        return (self.response @ np.transpose(R, (0, 2, 1))).reshape(-1, 3)
