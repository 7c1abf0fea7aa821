"""Geometry of one sensor (paper, section III-B and Fig. 5).

Frames: {0} is the sensor's nominal frame at the centre of the device, z along
the tool shaft towards the tip. {S_i} is chip i: z out of the chip's face, y
along the shaft's direction (tilted with the chip), x tangential. The magnet
frame {M_i} has the chip's orientation, 6 mm further along the chip's z. The
chips ride on the centre piece (frame {C}, equal to {0} at no load); the
magnets sit in the shell, fixed in {0}. Lengths in m.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from ftsensord.model import se3
from ftsensord.model.magnet import cylinder_moment

#: The paper's magnet, K&J D101-N52: 1/16" diameter, 1/32" thick, Br about 1.45 T.
D101_RADIUS_M = 1.5875e-3 / 2
D101_LENGTH_M = 0.79375e-3
D101_BR_T = 1.45

#: A gradient direction counts as apart from a load and a uniform field when at least half
#: of it (0.5 of its unit length) lies outside the flux they make: on the drawn ring the
#: in-plane parts lie wholly outside (1.0) and the other three inside (0); an as-built
#: part's chip tilts (1.5 deg) move either by under 0.1 (tests/test_stray.py).
SEPARABLE_GRADIENT = 0.5


#: The five parts of a traceless symmetric gradient G: xx - zz, yy - zz, and the symmetric
#: xy, xz, yz (each pair (i, j): the entry it sets; a diagonal one sets -1 at zz too).
GRADIENT_PARTS = ((0, 0), (1, 1), (0, 1), (0, 2), (1, 2))


def gradient_basis() -> np.ndarray:
    """The five unit parts E_k (5, 3, 3) of `GRADIENT_PARTS`."""
    E = np.zeros((5, 3, 3))
    for k, (i, j) in enumerate(GRADIENT_PARTS):
        E[k, i, j] = E[k, j, i] = 1.0
        if i == j:
            E[k, 2, 2] = -1.0
    return E


def separable_gradient(H: np.ndarray, room: np.ndarray | None, gradient: np.ndarray) -> np.ndarray:
    """The directions (24 x k, orthonormal) of a field's gradient (``gradient``, e.g.
    `SensorGeometry.gradient_directions`) that the chips can tell from a deflection
    (``H``'s columns) and a uniform field (``room``'s): the part of the gradient's span
    outside theirs, where it is at least `SEPARABLE_GRADIENT` of a direction. They are
    orthogonal to H and room, so projecting them out costs a load nothing it is seen by."""
    span, _ = np.linalg.qr(H if room is None else np.hstack([H, room]))
    outside = gradient - span @ (span.T @ gradient)
    u, s, _ = np.linalg.svd(outside, full_matrices=False)
    return u[:, s >= SEPARABLE_GRADIENT]


@dataclass(frozen=True)
class SensorGeometry:
    """Nominal chip and magnet placement of one sensor, in frame {0}.

    ``chip_R[i]`` is R_0Si (columns: the chip's x, y, z axes), ``chip_p[i]``
    its position; ``magnet_p[i]`` and ``magnet_axis[i]`` (unit, the direction
    of magnetisation) place magnet i. All magnets share one size and nominal
    Br; ``magnet_strength[i]`` (default 1) is magnet i's remanence relative to
    it, as an as-built part's magnets differ by a few %.
    """

    chip_R: np.ndarray
    chip_p: np.ndarray
    magnet_p: np.ndarray
    magnet_axis: np.ndarray
    magnet_radius_m: float = D101_RADIUS_M
    magnet_length_m: float = D101_LENGTH_M
    magnet_br_t: float = D101_BR_T
    magnet_strength: np.ndarray | None = None

    @property
    def n_chips(self) -> int:
        return len(self.chip_p)

    @property
    def magnet_moment_am2(self) -> float:
        return cylinder_moment(self.magnet_radius_m, self.magnet_length_m, self.magnet_br_t)

    @cached_property
    def magnet_R(self) -> np.ndarray:
        """Rotation of each magnet's own frame (z along its axis), for the cylinder field."""
        return np.array([frame_with_z(a) for a in self.magnet_axis])

    @cached_property
    def strengths(self) -> np.ndarray:
        """Each magnet's remanence relative to ``magnet_br_t`` (n,): ones unless as built."""
        return (
            np.ones(self.n_chips) if self.magnet_strength is None else np.asarray(self.magnet_strength, float)
        )

    def room_directions(self) -> np.ndarray:
        """The 3 directions (24 x 3, orthonormal columns) a uniform field makes in the
        stacked flux: a field u in frame {0} adds [R_01^T u; ...; R_0n^T u].

        Since sum_i R_i R_i^T = n I, the stacked R_i^T divided by sqrt(n) is already
        orthonormal; the QR below only keeps that exact for an as-built geometry too.
        """
        stacked = np.concatenate([R.T for R in self.chip_R], axis=0)
        q, _ = np.linalg.qr(stacked)
        return q

    def gradient_directions(self) -> np.ndarray:
        """The 5 directions (24 x 5, orthonormal columns) a field's first-order gradient
        makes in the stacked flux: a field u + G p near the sensor (p in m, frame {0}; G in
        T/m, symmetric and traceless as a curl- and divergence-free field's is) adds
        R_0i^T G p_i to chip i. Basis G: xx - zz, yy - zz, and the symmetric xy, xz, yz.

        On the drawn ring (chips in one plane, 8-fold symmetric) only the two in-plane
        parts xx - yy and xy are apart from a load and a uniform field: G_zz's pattern is an
        axial push's and a uniform B_z's, G_xz's and G_yz's a tilt's and a uniform B_x's,
        B_y's (docs/design/physics.md, "A motor's field"). `separable_gradient` keeps those two.
        """
        q, _ = np.linalg.qr(self.gradient_flux())
        return q

    def gradient_flux(self) -> np.ndarray:
        """F (24 x 5): each `gradient_basis` part's flux at the chips, R_0i^T E_k p_i
        stacked (T per T/m); `gradient_directions` is its orthonormal span."""
        E = gradient_basis()
        return np.einsum("nba,kbc,nc->nak", self.chip_R, E, self.chip_p).reshape(-1, 5)

    def magnet_in_chip(self) -> np.ndarray:
        """Nominal position of each chip's own magnet in the chip's frame (n x 3)."""
        return np.einsum("nji,nj->ni", self.chip_R, self.magnet_p - self.chip_p)

    @classmethod
    def ring(
        cls, n: int = 8, radius_m: float = 8e-3, tilt_deg: float = 25.0, gap_m: float = 6e-3
    ) -> SensorGeometry:
        """The paper's layout: ``n`` chips on a ring around the shaft, faces
        ``tilt_deg`` from the shaft axis, each magnet ``gap_m`` out along its
        chip's z. The ring radius is not given in the paper; 8 mm leaves room
        for a 5 mm laparoscopic shaft."""
        tilt = math.radians(tilt_deg)
        chip_R, chip_p = [], []
        for i in range(n):
            phi = 2 * math.pi * i / n
            e_r = np.array([math.cos(phi), math.sin(phi), 0.0])
            e_t = np.array([-math.sin(phi), math.cos(phi), 0.0])
            e_z = np.array([0.0, 0.0, 1.0])
            y = math.cos(tilt) * e_z - math.sin(tilt) * e_r  # along the shaft, tilted with the face
            z = math.cos(tilt) * e_r + math.sin(tilt) * e_z  # out of the face
            chip_R.append(np.stack([e_t, y, z], axis=1))
            chip_p.append(radius_m * e_r)
        chip_R_arr, chip_p_arr = np.array(chip_R), np.array(chip_p)
        axes = chip_R_arr[:, :, 2]
        return cls(chip_R_arr, chip_p_arr, chip_p_arr + gap_m * axes, axes.copy())


def frame_with_z(axis: np.ndarray) -> np.ndarray:
    """A rotation whose third column is the unit vector ``axis`` (any x, y will do
    for a body symmetric about it)."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, axis)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(axis, x), axis], axis=1)


def as_built(
    nominal: SensorGeometry,
    rng: np.random.Generator,
    *,
    magnet_position_m: float = 0.0,
    magnet_strength_rel: float = 0.0,
    chip_tilt_rad: float = 0.0,
) -> SensorGeometry:
    """One hand-made sensor drawn from ``nominal`` with the given standard deviations:
    each magnet moved by N(0, magnet_position_m) per axis (m, frame {0}) and its
    remanence scaled by 1 + N(0, magnet_strength_rel); each chip turned by a rotation
    vector of N(0, chip_tilt_rad) per axis (rad, the chip's frame), so its tilt
    angle has RMS sqrt(3) chip_tilt_rad. The magnets' axes stay those of the
    nominal part (a disc magnet pressed into its pocket sits square to it).
    Deterministic in ``rng``: the caller draws once per sensor, with its seed.
    """
    n = nominal.n_chips
    magnet_shift = rng.normal(0.0, 1.0, (n, 3)) * magnet_position_m
    strength = 1.0 + rng.normal(0.0, 1.0, n) * magnet_strength_rel
    if np.any(strength <= 0):
        raise ValueError(f"a remanence tolerance of {magnet_strength_rel:.0%} drew a magnet with no field")
    tilts = rng.normal(0.0, 1.0, (n, 3)) * chip_tilt_rad
    chip_R = np.array([R @ se3.exp_so3(w) for R, w in zip(nominal.chip_R, tilts, strict=True)])
    return SensorGeometry(
        chip_R,
        nominal.chip_p.copy(),
        nominal.magnet_p + magnet_shift,
        nominal.magnet_axis.copy(),
        nominal.magnet_radius_m,
        nominal.magnet_length_m,
        nominal.magnet_br_t,
        nominal.strengths * strength,
    )
