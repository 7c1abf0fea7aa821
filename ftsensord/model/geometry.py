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

from .magnet import cylinder_moment

#: The paper's magnet, K&J D101-N52: 1/16" diameter, 1/32" thick, Br about 1.45 T.
D101_RADIUS_M = 1.5875e-3 / 2
D101_LENGTH_M = 0.79375e-3
D101_BR_T = 1.45


@dataclass(frozen=True)
class SensorGeometry:
    """Nominal chip and magnet placement of one sensor, in frame {0}.

    ``chip_R[i]`` is R_0Si (columns: the chip's x, y, z axes), ``chip_p[i]``
    its position; ``magnet_p[i]`` and ``magnet_axis[i]`` (unit, the direction
    of magnetisation) place magnet i. All magnets share one size and Br.
    """

    chip_R: np.ndarray
    chip_p: np.ndarray
    magnet_p: np.ndarray
    magnet_axis: np.ndarray
    magnet_radius_m: float = D101_RADIUS_M
    magnet_length_m: float = D101_LENGTH_M
    magnet_br_t: float = D101_BR_T

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

    def magnet_in_chip(self) -> np.ndarray:
        """Nominal position of each chip's own magnet in the chip's frame (n x 3)."""
        return np.einsum("nji,nj->ni", self.chip_R, self.magnet_p - self.chip_p)

    @classmethod
    def ring(cls, n: int = 8, radius_m: float = 8e-3, tilt_deg: float = 25.0,
             gap_m: float = 6e-3) -> SensorGeometry:
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
