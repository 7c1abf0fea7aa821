"""Field models against closed forms and quadrature."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from ftsensord.model.magnet import (
    MU0_OVER_4PI,
    cel,
    cylinder_field,
    cylinder_moment,
    dipole_field,
    octupole_field,
    octupole_ratio,
)

A, L, BR = 1.5875e-3 / 2, 0.79375e-3, 1.45  # the paper's D101-N52


def cel_by_quadrature(kc, p, c, s, n=200_001):
    phi = np.linspace(0, np.pi / 2, n)
    co, si = np.cos(phi) ** 2, np.sin(phi) ** 2
    f = (c * co + s * si) / ((co + p * si) * np.sqrt(co + kc**2 * si))
    return np.trapezoid(f, phi)


@given(st.floats(0.01, 1.0), st.floats(0.01, 4.0), st.floats(-2, 2), st.floats(-2, 2))
def test_cel_matches_its_defining_integral(kc, p, c, s):
    assert float(cel(kc, p, c, s)) == pytest.approx(cel_by_quadrature(kc, p, c, s), rel=1e-8, abs=1e-10)


def test_cel_gives_the_complete_elliptic_integral_of_the_first_kind():
    # K(k) = cel(sqrt(1 - k^2), 1, 1, 1); K(0) = pi/2, K(1/sqrt2) = 1.8540746773013719.
    assert float(cel(1.0, 1.0, 1.0, 1.0)) == pytest.approx(np.pi / 2, rel=1e-15)
    assert float(cel(np.sqrt(0.5), 1.0, 1.0, 1.0)) == pytest.approx(1.8540746773013719, rel=1e-14)
    with pytest.raises(ValueError):
        cel(0.0, 1.0, 1.0, 1.0)


@pytest.mark.parametrize("z", [0.5e-3, 1e-3, 3e-3, 6e-3, 20e-3, -6e-3])
def test_cylinder_on_axis_matches_the_textbook_formula(z):
    b = L / 2
    expected = BR / 2 * ((z + b) / np.hypot(z + b, A) - (z - b) / np.hypot(z - b, A))
    field = cylinder_field(np.array([0.0, 0.0, z]), A, L, BR)
    assert field[2] == pytest.approx(expected, rel=1e-12)
    assert field[0] == 0.0 and field[1] == 0.0


@given(st.floats(0, 2 * np.pi), st.floats(0.05, np.pi - 0.05))
def test_cylinder_tends_to_the_dipole_far_away(phi, theta):
    direction = np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
    m = np.array([0.0, 0.0, cylinder_moment(A, L, BR)])
    for dist, tol in ((0.2, 1e-4), (2.0, 1e-6)):  # the error falls as (a / r)^2
        r = direction * dist
        exact, dipole = cylinder_field(r, A, L, BR), dipole_field(r, m)
        assert np.linalg.norm(exact - dipole) <= tol * np.linalg.norm(dipole)


def test_cylinder_field_is_divergence_and_curl_free_outside():
    r0, h = np.array([2e-3, -1e-3, 4e-3]), 1e-7
    jac = np.zeros((3, 3))
    for i in range(3):
        e = np.zeros(3)
        e[i] = h
        jac[:, i] = (cylinder_field(r0 + e, A, L, BR) - cylinder_field(r0 - e, A, L, BR)) / (2 * h)
    scale = np.abs(jac).max()
    assert abs(np.trace(jac)) < 1e-6 * scale
    assert np.allclose(jac, jac.T, atol=1e-6 * scale)


def test_dipole_on_axis_and_broadcasting():
    m = np.array([0.0, 0.0, 1.8e-3])
    r = np.array([[0.0, 0.0, 6e-3], [6e-3, 0.0, 0.0]])
    field = dipole_field(r, m)
    assert field[0, 2] == pytest.approx(1e-7 * 2 * 1.8e-3 / 6e-3**3)
    assert field[1, 2] == pytest.approx(-1e-7 * 1.8e-3 / 6e-3**3)  # equator: -m/r^3


@pytest.mark.parametrize("z", [0.5e-3, 1e-3, 3e-3, 6e-3, -2e-3])
@pytest.mark.parametrize("phi", [0.0, np.pi / 2])
def test_cylinder_field_at_the_magnets_radius_beyond_its_faces(z, phi):
    """rho = a exactly (gamma = 0), |z| > L/2: outside the magnet, where one elliptic
    integral has no value on its own. The field there is the limit from both sides:
    within 1e-9 relative of rho = a (1 -+ 1e-10). Why 1e-9: the field's slope in rho is
    about 3 B / a, so 1e-10 of a moves it ~3e-10 relative; round-off is far below."""
    at = np.array([A * np.cos(phi), A * np.sin(phi), z])
    assert np.hypot(at[0], at[1]) == A  # the singular point itself, not a neighbour
    exact = cylinder_field(at, A, L, BR)
    assert np.all(np.isfinite(exact))
    for side in (1 - 1e-10, 1 + 1e-10):
        near = cylinder_field(np.array([A * side * np.cos(phi), A * side * np.sin(phi), z]), A, L, BR)
        assert np.allclose(exact, near, rtol=1e-9, atol=1e-9 * np.linalg.norm(exact))


def test_cylinder_field_on_the_side_face_is_the_mean_of_its_two_sides():
    """On the side face (rho = a, |z| < L/2) B_z jumps by Br (the surface current): the
    value there is the mean of inside and outside; on the rim edges it stays singular."""
    z = 0.2e-3
    inside, outside = (cylinder_field(np.array([A * f, 0.0, z]), A, L, BR) for f in (1 - 1e-12, 1 + 1e-12))
    assert inside[2] - outside[2] == pytest.approx(BR, rel=1e-6)
    assert cylinder_field(np.array([A, 0.0, z]), A, L, BR)[2] == pytest.approx(
        0.5 * (inside[2] + outside[2]), rel=1e-9
    )
    with pytest.raises(ValueError):
        cylinder_field(np.array([A, 0.0, L / 2]), A, L, BR)


@pytest.mark.parametrize(
    ("distance_m", "octupole_limit", "dipole_floor"),
    [(2e-3, 0.009, 0.15), (3e-3, 0.0014, 0.06), (6e-3, 7e-5, 0.015)],
)
def test_the_octupole_brings_the_dipole_to_the_cylinders_field(distance_m, octupole_limit, dipole_floor):
    """The D101 (L = D/2) is no point dipole near its chip: 18 % off at 2 mm, 1.8 % at the
    6 mm gap. With the octupole (the next term of its axial field's series) the largest
    error over all directions is 0.9 %, 0.13 %, 0.006 %: the figures octupole_field's
    docstring quotes."""
    m = cylinder_moment(A, L, BR)
    q = np.array(MU0_OVER_4PI * m * octupole_ratio(A, L))
    axis = np.array([0, 0, 1.0])
    worst_octupole = worst_dipole = 0.0
    for theta in np.linspace(0, np.pi, 25):
        r = distance_m * np.array([np.sin(theta), 0.0, np.cos(theta)])
        exact = cylinder_field(r, A, L, BR)
        dipole = dipole_field(r, m * axis)
        scale = np.linalg.norm(exact)
        worst_dipole = max(worst_dipole, np.linalg.norm(dipole - exact) / scale)
        worst_octupole = max(
            worst_octupole, np.linalg.norm(dipole + octupole_field(r, axis, q)[0] - exact) / scale
        )
    assert worst_octupole < octupole_limit and worst_dipole > dipole_floor


def test_octupole_ratio_vanishes_for_the_dipole_like_cylinder():
    """kappa = -(3 a^2 - 4 b^2)/4: zero at L/D = sqrt(3)/2 (no octupole), -a^2/2 for L = a."""
    assert octupole_ratio(1e-3, np.sqrt(3) * 1e-3) == pytest.approx(0.0, abs=1e-18)  # round-off of 1e-6
    assert octupole_ratio(1e-3, 1e-3) == pytest.approx(-0.5e-6)


@given(
    st.tuples(*[st.floats(-4e-3, 4e-3)] * 3).filter(lambda r: np.linalg.norm(r) > 1.5e-3).map(np.array),
    st.tuples(*[st.floats(-1, 1)] * 3).filter(lambda n: np.linalg.norm(n) > 0.1).map(np.array),
)
def test_octupole_gradient_matches_finite_differences(r, n):
    axis = n / np.linalg.norm(n)
    q = np.array(-2e-14)
    _, G = octupole_field(r, axis, q)
    h = 1e-9  # central differences: error ~h^2 x third derivative, far below 1e-5 here
    numeric = np.stack(
        [
            (octupole_field(r + h * e, axis, q, False)[0] - octupole_field(r - h * e, axis, q, False)[0])
            / (2 * h)
            for e in np.eye(3)
        ],
        axis=1,
    )
    assert np.allclose(G, numeric, rtol=1e-5, atol=1e-6 * np.abs(numeric).max())
    assert np.allclose(G, G.T, atol=1e-9 * np.abs(G).max())  # curl-free
