"""Magnetic field of the sensor's magnets: a point dipole (and its gradient,
`dipole_pairs`), and the exact field of a uniformly, axially magnetised cylinder.

All positions in m, moments in A m^2, remanence and fields in T. Arrays
broadcast: ``r`` may be (..., 3).

The cylinder field is Derby & Olbert's closed form (Am. J. Phys. 78, 229,
2010) with Bulirsch's generalised complete elliptic integral ``cel``.
"""

from __future__ import annotations

import math
from typing import TypeVar

import numpy as np

#: A temperature difference (K) or an array of them: the laws act element by element.
FloatOrArray = TypeVar("FloatOrArray", float, np.ndarray)

_EYE3 = np.eye(3)

#: mu_0 / (4 pi), in T m / A.
MU0_OVER_4PI = 1e-7

#: NdFeB loses about 0.12 % of its remanence per kelvin (N52 grade, typical; reversible),
#: from 25 degC: the field of a magnet scales with 1 + NDFEB_BR_TEMPCO_PER_K (T - 25 degC).
NDFEB_BR_TEMPCO_PER_K = -1.2e-3


def remanence_factor(delta_k: FloatOrArray) -> FloatOrArray:
    """Br(T) / Br(25 degC) of NdFeB ``delta_k`` kelvin above 25 degC (both field models scale with it)."""
    return 1.0 + NDFEB_BR_TEMPCO_PER_K * delta_k


#: Relative tolerance of `cel`'s iteration. The iteration converges
#: quadratically (an arithmetic-geometric mean), so stopping at 1e-14 costs one
#: step more than 1e-8 and leaves the result at double precision.
CEL_TOL = 1e-14


def dipole_field(r: np.ndarray, m: np.ndarray) -> np.ndarray:
    """B (T) at offset ``r`` (m) from a point dipole of moment ``m`` (A m^2).

    B = mu0/(4 pi) (3 r (r.m) / |r|^5 - m / |r|^3). Undefined at r = 0.
    """
    return dipole_pairs(np.asarray(r, dtype=float), np.asarray(m, dtype=float), gradient=False)[0]


def dipole_pairs(r: np.ndarray, m: np.ndarray, gradient: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """Field (..., 3) and its gradient dB/dr (..., 3, 3; None unless asked) of point
    dipoles of moment ``m`` (A m^2) at offsets ``r`` (m) from them, T and T/m, per pair:
    the sums over magnets are the caller's (the calibration needs them one by one)."""
    B, parts = _dipole_field(r, m)
    return B, (_dipole_gradient(r, m, *parts) if gradient else None)


def _dipole_field(r: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
    """`dipole_pairs`'s field, and what its gradient reuses (d^2, r.m, k / d^5)."""
    # As few numpy operations as the formulas allow: at 8 x 8 pairs each costs more in
    # call overhead than in arithmetic, and the calibration's fit runs this every iteration
    # (the estimator has its own, `fluxmodel.FluxModel._fields`).
    d2 = np.einsum("...i,...i->...", r, r)[..., None]
    rm = np.einsum("...i,...i->...", r, m)[..., None]
    k_d5 = MU0_OVER_4PI / (d2 * d2 * np.sqrt(d2))
    return k_d5 * (3 * rm * r - d2 * m), (d2, rm, k_d5)


def _dipole_gradient(
    r: np.ndarray, m: np.ndarray, d2: np.ndarray, rm: np.ndarray, k_d5: np.ndarray
) -> np.ndarray:
    """dB/dr of a dipole: k (3 (m r^T + r m^T + (r.m) I) / d^5 - 15 (r.m) r r^T / d^7)."""
    mr = m[..., :, None] * r[..., None, :]
    outer = mr + np.swapaxes(mr, -1, -2) + rm[..., None] * _EYE3
    return k_d5[..., None] * (3 * outer - (15 * rm / d2)[..., None] * (r[..., :, None] * r[..., None, :]))


def cel(kc: np.ndarray, p: np.ndarray, c: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Bulirsch's complete elliptic integral, vectorised:

    cel = int_0^{pi/2} (c cos^2 + s sin^2) / ((cos^2 + p sin^2) sqrt(cos^2 + kc^2 sin^2)) dphi

    for p > 0 and kc != 0 (the cases the cylinder field needs).
    """
    kc, p, c, s = np.broadcast_arrays(*(np.asarray(x, dtype=float) for x in (kc, p, c, s)))
    if np.any(kc == 0) or np.any(p <= 0):
        raise ValueError("cel needs kc != 0 and p > 0")
    k = np.abs(kc)
    pp = np.sqrt(p)
    ss = s / pp
    cc = c.copy()
    em = np.ones_like(k)
    f = cc
    cc = cc + ss / pp
    g = k / pp
    ss = 2.0 * (ss + f * g)
    pp = g + pp
    g = em.copy()
    em = k + em
    kk = k.copy()
    for _ in range(60):  # quadratic convergence: ~6 steps for double precision
        if np.all(np.abs(g - k) <= g * CEL_TOL):
            break
        k = 2.0 * np.sqrt(kk)
        kk = k * em
        f = cc
        cc = cc + ss / pp
        g = kk / pp
        ss = 2.0 * (ss + f * g)
        pp = g + pp
        g = em
        em = k + em
    return (math.pi / 2) * (ss + cc * em) / (em * (em + pp))


def cylinder_field(r: np.ndarray, radius: float, length: float, br: float) -> np.ndarray:
    """B (T) at ``r`` (m, the magnet's frame: origin at its centre, z along its
    magnetisation) of a cylinder of ``radius`` and ``length`` (m) with remanence
    ``br`` (T). Exact and finite everywhere outside the magnet, including the
    cylinder rho = radius beyond its end faces; singular only on its two rim edges
    (rho = radius, z = +-length/2), which are on the magnet.
    """
    r = np.asarray(r, dtype=float)
    x, y, z = r[..., 0], r[..., 1], r[..., 2]
    rho = np.hypot(x, y)
    a, b = radius, length / 2
    b0 = br / math.pi
    zp, zm = z + b, z - b
    inv_p = 1.0 / np.sqrt(zp**2 + (rho + a) ** 2)
    inv_m = 1.0 / np.sqrt(zm**2 + (rho + a) ** 2)
    alpha_p, alpha_m = a * inv_p, a * inv_m
    beta_p, beta_m = zp * inv_p, zm * inv_m
    gamma = (a - rho) / (a + rho)
    k_p = np.sqrt((zp**2 + (a - rho) ** 2) / (zp**2 + (a + rho) ** 2))
    k_m = np.sqrt((zm**2 + (a - rho) ** 2) / (zm**2 + (a + rho) ** 2))
    # The four integrals (B_rho and B_z, at both end faces) in one vectorised call.
    one = np.ones_like(rho)
    # At rho = a exactly (gamma = 0) cel(k, gamma^2, 1, gamma) has no value: its
    # integrand spikes to 1/gamma over a width gamma near phi = pi/2, adding
    # +-pi/(2 k) for gamma -> 0+-. Outside the magnet (|z| > b) the two end faces'
    # spikes cancel in beta_p/k_p - beta_m/k_m (both equal sign(z)), so B_z is
    # continuous there and its value is the mean of the two sides: cel(k, 1, 1, 1),
    # the complete elliptic integral K. (On the side face, |z| < b, B_z jumps by Br:
    # the mean is the surface's own value.) An exact-zero branch suffices: for any
    # gamma != 0, however small, the AGM in `cel` resolves the spike (tests/test_magnet.py).
    on_rim = gamma == 0
    g2 = np.where(on_rim, 1.0, gamma**2)
    s_z = np.where(on_rim, 1.0, gamma)
    c = cel(
        np.stack([k_p, k_m, k_p, k_m]), np.stack([one, one, g2, g2]), one, np.stack([-one, -one, s_z, s_z])
    )
    b_rho = b0 * (alpha_p * c[0] - alpha_m * c[1])
    b_z = b0 * a / (a + rho) * (beta_p * c[2] - beta_m * c[3])
    # B_rho is radial: split it along x and y (on the axis, rho = 0, it is 0).
    with np.errstate(invalid="ignore", divide="ignore"):
        cos_phi = np.where(rho > 0, x / rho, 0.0)
        sin_phi = np.where(rho > 0, y / rho, 0.0)
    return np.stack([b_rho * cos_phi, b_rho * sin_phi, b_z], axis=-1)


def cylinder_moment(radius: float, length: float, br: float) -> float:
    """Dipole moment (A m^2) of the cylinder: m = Br V / mu_0."""
    return br * math.pi * radius**2 * length / (4 * math.pi * MU0_OVER_4PI)


def octupole_ratio(radius: float, length: float) -> float:
    """The cylinder's octupole relative to its dipole (m^2): kappa = -(3 a^2 - 4 b^2) / 4,
    a the radius, b half the length. On its axis the field is
    mu0 m / (2 pi z^3) (1 + 2 kappa / z^2 + O(z^-4)) (the series of Derby & Olbert's
    axial field); zero for a cylinder with L/D = sqrt(3)/2, -a^2/2 for the D101 (L = a)."""
    b = length / 2
    return -(3 * radius**2 - 4 * b**2) / 4


def octupole_field(
    r: np.ndarray, axis: np.ndarray, q: np.ndarray, gradient: bool = True
) -> tuple[np.ndarray, np.ndarray | None]:
    """Field (..., 3; T) and gradient dB/dr (..., 3, 3; T/m; None unless asked) of the
    octupole term at offsets ``r`` (m) from magnets of unit ``axis``, strength ``q`` (...,
    T m^5: mu0/(4 pi) |m| kappa, `octupole_ratio`). Its scalar potential q P_3(s/d) / d^4
    gives B = q/2 (A r - C n), A = 35 s^3/d^9 - 15 s/d^7, C = 15 s^2/d^7 - 3/d^5, s = r.n:
    the dipole's next term outside the sphere around the magnet (a cylinder has no even
    ones). With it the D101's field is within 0.9 % of the exact one from 2 mm of its
    centre (a chip saturates nearer), 0.006 % at 6 mm; the dipole alone is 18 % and 1.8 %
    off (tests/test_magnet.py)."""
    # Written as A = s d^-7 (35 c2 - 15), C = d^-5 (15 c2 - 3), c2 = s^2/d^2 (cos^2 of the
    # angle from the axis): few operations, as the estimator calls this every iteration.
    d2 = np.einsum("...i,...i->...", r, r)[..., None]
    s = np.einsum("...i,...i->...", r, axis)[..., None]
    inv2 = 1.0 / d2
    c2 = s * s * inv2
    hq = 0.5 * q[..., None] * inv2 * inv2 * inv2 * np.sqrt(inv2)  # q/2 d^-7
    a = hq * s * (35 * c2 - 15)  # q/2 A
    B = a * r - (hq * d2 * (15 * c2 - 3)) * axis
    if not gradient:
        return B, None
    # dB/dr = q/2 (A I + (105 c2 - 15) d^-7 (r n^T + n r^T) + (105 - 315 c2) s d^-9 r r^T
    # - 30 s d^-7 n n^T): symmetric, as a curl-free field's gradient is.
    rn = r[..., :, None] * axis[..., None, :]
    G = (
        (hq * (105 * c2 - 15))[..., None] * (rn + np.swapaxes(rn, -1, -2))
        + (hq * s * inv2 * (105 - 315 * c2))[..., None] * (r[..., :, None] * r[..., None, :])
        - (30 * hq * s)[..., None] * (axis[..., :, None] * axis[..., None, :])
        + a[..., None] * np.eye(3)
    )
    return B, G
