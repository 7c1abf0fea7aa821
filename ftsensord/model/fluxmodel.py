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

from ftsensord.model.geometry import SensorGeometry
from ftsensord.model.magnet import MU0_OVER_4PI, octupole_ratio

_EYE3 = np.eye(3)
#: hat(x) = (x @ _HAT).reshape(3, 3), so rows of vectors give their skew matrices in one
#: product: hat(x)_jk = -eps_jkl x_l (`se3.hat`).
_HAT = np.zeros((3, 9))
_HAT[2, 1], _HAT[1, 2], _HAT[0, 5] = -1.0, 1.0, -1.0
_HAT[2, 3], _HAT[1, 6], _HAT[0, 7] = 1.0, -1.0, 1.0


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
        """S as a matrix per chip (n, 3, 3)."""
        return self._constants.response

    @property
    def _constants(self) -> _Constants:
        """What the field needs that does not change with the pose: kept while the scale,
        the geometry and the moments are those it was made from (the same objects, and the
        same numbers: an array changed in place is seen)."""
        g, scale = self.geometry, self.scale
        cached = self.__dict__.get("_constants_cache")
        if (
            cached is not None
            and cached[0] is scale
            and cached[1] is g
            and cached[2]
            == (self.moment_am2, self.crosstalk, self.octupole, scale.tobytes(), g.strengths.tobytes())
        ):
            return cached[3]
        constants = _Constants.build(self)
        self.__dict__["_constants_cache"] = (
            scale,
            g,
            (self.moment_am2, self.crosstalk, self.octupole, scale.tobytes(), g.strengths.tobytes()),
            constants,
        )
        return constants

    def _fields(
        self, T: np.ndarray, gradient: bool = True
    ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        """World field B (n, 3), its gradient G (n, 3, 3; None unless asked), chip positions p."""
        # The estimator asks the field at a pose (is the step better?) and then, at the
        # same pose, its gradient too: the field's part is kept for that second call.
        c = self._constants
        last = self.__dict__.get("_last_field")
        if (
            last is not None and last[0] is T and last[2] is c and last[1] == T.tobytes()
        ):  # bytes: array_equal costs 5 us
            _, _, _, B, p, r, parts = last
        else:
            # As few numpy operations as the formulas allow: on 8 x 8 pairs each costs
            # more in call overhead than in arithmetic, and the estimator runs this for
            # every sample. Both terms from one set of distances: the dipole's sum over
            # the magnets as two products, the octupole on the pairs' diagonal (views).
            p = c.chip_p @ T[:3, :3].T + T[:3, 3]
            r = p[:, None, :] - c.magnet_p  # (chip, magnet, 3)
            d2 = np.einsum("cmi,cmi->cm", r, r)
            rm3 = np.einsum("cmi,mi->cm", r, c.m3)  # 3 mu0/(4 pi) r.m
            inv = 1.0 / d2
            k3 = inv * np.sqrt(inv)  # d^-3
            if c.own_only is not None:
                k3 = k3 * c.own_only  # each chip's own magnet alone
            k5 = k3 * inv
            # B = sum_m mu0/(4 pi) (3 (r.m) r / d^5 - m / d^3)
            a = k5 * rm3
            B = np.einsum("cm,cmi->ci", a, r) - k3 @ c.m
            octupole = None
            if c.half_q is not None:
                own = r.reshape(-1, 3)[:: c.n + 1]  # chip i's offset from magnet i
                inv_own = inv.ravel()[:: c.n + 1]
                s = np.einsum("ci,ci->c", own, c.axis)
                c2 = s * s * inv_own  # cos^2 of the angle from the magnet's axis
                hq = c.half_q * k5.ravel()[:: c.n + 1] * inv_own  # q/2 d^-7
                # octupole_field's B = q/2 (A r - C n), A = s d^-7 (35 c2 - 15), C = d^-5 (15 c2 - 3)
                a_own = hq * s * (35 * c2 - 15)
                B = B + a_own[:, None] * own - (hq * (15 * c2 - 3) / inv_own)[:, None] * c.axis
                octupole = (s, c2, hq, a_own, inv_own)
            parts = (inv, k5, a, octupole)
            self.__dict__["_last_field"] = (T, T.tobytes(), c, B, p, r, parts)
        return B, (_gradient(c, r, *parts) if gradient else None), p

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
        # S R_chip^T R_T^T B, R_T^T B as the rows B R_T: two products on (n, 3), not (n, 3, 3).
        return (self._constants.response_chip @ (B @ T[:3, :3])[:, :, None]).ravel() + self.offset_t.ravel()

    def predict_and_jacobian(
        self, T: np.ndarray, u: np.ndarray | None = None, background: bool = False
    ) -> tuple[np.ndarray, np.ndarray]:
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
        c = self._constants
        SRt = c.response_chip @ T[:3, :3].T  # S R^T, R = R_T R_chip
        hats = (np.concatenate([B, p]) @ _HAT).reshape(2, c.n, 3, 3)  # hat(B), hat(p): one product
        # [db/dv, db/dw, (db/du), b] as one product of S R^T with their columns side by side.
        columns = [G, hats[0] - G @ hats[1], *([c.eye] if background else []), B[:, :, None]]
        full = SRt @ np.concatenate(columns, axis=2)
        b = full[:, :, -1] + self.offset_t
        return b.ravel(), full[:, :, :-1].reshape(3 * c.n, -1)

    def background_directions(self, T: np.ndarray | None = None) -> np.ndarray:
        """U (3n, 3): the flux a unit background field along x, y, z of {0} adds (T/T)."""
        R = self.geometry.chip_R if T is None else np.einsum("ij,njk->nik", T[:3, :3], self.geometry.chip_R)
        return (self.response @ np.transpose(R, (0, 2, 1))).reshape(-1, 3)


def _gradient(
    c: _Constants,
    r: np.ndarray,
    inv: np.ndarray,
    k5: np.ndarray,
    a: np.ndarray,
    octupole: tuple[np.ndarray, ...] | None,
) -> np.ndarray:
    """dB/dr at each chip (n, 3, 3; T/m) from `FluxModel._fields`'s parts: r (chip, magnet,
    3), 1/d^2, d^-5 and a = 3 mu0/(4 pi) (r.m) d^-5 per pair, and the octupole's."""
    # A dipole's is mu0/(4 pi) (3 (m r^T + r m^T + (r.m) I) / d^5 - 15 (r.m) r r^T / d^7);
    # summed over the magnets: W + W^T + sum_m v r r^T + (sum_m a) I, W = sum_m w m r^T,
    # as two batched products where 64 outer products were.
    w, v, diag = 3 * k5, -5 * a * inv, a.sum(axis=1)
    if octupole is not None:
        # octupole_field's: q/2 (A I + (105 c2 - 15) d^-7 (r n^T + n r^T)
        # + (105 - 315 c2) s d^-9 r r^T - 30 s d^-7 n n^T), n = m / |m|, on the own pairs.
        s, c2, hq, a_own, inv_own = octupole
        w.ravel()[:: c.n + 1] += hq * (105 * c2 - 15) * c.inv_m  # views: w's diagonal, in place
        v.ravel()[:: c.n + 1] += hq * s * inv_own * (105 - 315 * c2)
        diag = diag + a_own
    W = np.matmul(np.swapaxes(w[:, :, None] * c.m, 1, 2), r)
    G = (
        W
        + np.swapaxes(W, 1, 2)
        + np.matmul(np.swapaxes(v[:, :, None] * r, 1, 2), r)
        + diag[:, None, None] * _EYE3
    )
    if octupole is not None:
        G = G - (30 * octupole[2] * octupole[0])[:, None, None] * c.axis_outer
    return G


@dataclass(frozen=True)
class _Constants:
    """A `FluxModel`'s pose-independent arrays (SI; frame {0})."""

    n: int
    chip_p: np.ndarray  # (n, 3) chip positions at rest
    magnet_p: np.ndarray  # (n, 3)
    m: np.ndarray  # (n, 3) mu0/(4 pi) times each magnet's dipole moment, T m^3
    m3: np.ndarray  # 3 m
    axis: np.ndarray  # (n, 3) unit magnetisation
    half_q: np.ndarray | None  # (n,) half each octupole strength (T m^5); None without
    own_only: np.ndarray | None  # (n, n) the identity without crosstalk, else None
    response: np.ndarray  # S (n, 3, 3)
    response_chip: np.ndarray  # S R_chip^T (n, 3, 3): a pose's S R^T is this times R_T^T
    inv_m: np.ndarray  # (n,) 1 / |m|
    axis_outer: np.ndarray  # (n, 3, 3) n n^T
    eye: np.ndarray  # (n, 3, 3) identities (read-only views): db/du's columns before S R^T

    @staticmethod
    def build(model: FluxModel) -> _Constants:
        g = model.geometry
        s = np.asarray(model.scale, dtype=float)
        response = s.copy() if s.ndim == 3 else s[:, :, None] * np.eye(3)
        m = MU0_OVER_4PI * model.moment_am2 * g.strengths[:, None] * g.magnet_axis
        q = (
            MU0_OVER_4PI
            * model.moment_am2
            * g.strengths
            * octupole_ratio(g.magnet_radius_m, g.magnet_length_m)
        )
        # The geometry's own arrays, not copies: positions changed in place are used, as before.
        return _Constants(
            g.n_chips,
            np.asarray(g.chip_p, float),
            np.asarray(g.magnet_p, float),
            m,
            3 * m,
            np.asarray(g.magnet_axis, float),
            0.5 * q if model.octupole else None,
            None if model.crosstalk else np.eye(g.n_chips),
            response,
            response @ np.transpose(g.chip_R, (0, 2, 1)),
            1 / np.linalg.norm(m, axis=1),
            g.magnet_axis[:, :, None] * g.magnet_axis[:, None, :],
            np.broadcast_to(_EYE3, (g.n_chips, 3, 3)),
        )
