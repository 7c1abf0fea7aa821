"""Stray sources (issue 23): a motor's point dipole fixed in the world, seen by each chip
at its actual position and in its own frame, scaled over time; scene files that say so;
and what the run time makes of the field's gradient across the ring."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ftsensord.model import se3
from ftsensord.sim import load_scene
from ftsensord.sim.loads import FixedOrientation, StaticLoad
from ftsensord.sim.physics import PhysicalScene, SimSensor, StraySource

from .conftest import assert_names_file_and_key

ADDRS = tuple(range(0x0C, 0x14))


def independent_dipole(r: np.ndarray, m: np.ndarray) -> np.ndarray:
    """B (T) of a point dipole ``m`` (A m^2) at offset ``r`` (m): mu0/(4 pi) (3 r (m.r)/|r|^5 - m/|r|^3),
    written here from the textbook rather than taken from the project."""
    d = math.sqrt(float(r @ r))
    return 1e-7 * (3.0 * r * float(m @ r) / d**5 - m / d**3)


def test_a_stray_dipole_is_seen_at_each_chips_turned_and_deflected_position():
    sensor = SimSensor("s", ADDRS, centre_m=np.array([0.01, -0.02, 0.03]),
                       load=StaticLoad(np.array([5.0, -3.0, 8.0, 0.05, -0.04, 0.1])),
                       orientation=FixedOrientation(se3.exp_so3(np.array([0.4, -0.7, 1.1]))))
    source = StraySource(np.array([0.12, 0.05, -0.06]), np.array([0.5, -1.2, 1.5]))
    with_source = PhysicalScene([sensor], stray_sources=[source])
    without = PhysicalScene([sensor])
    R_w0 = sensor.orientation.rotation(0.0)
    T = se3.exp_se3(sensor.deflection(sensor.load.wrench(0.0)))
    for i, address in enumerate(ADDRS):
        chip_world = sensor.centre_m + R_w0 @ (T[:3, :3] @ sensor.geometry.chip_p[i] + T[:3, 3])
        R_world_chip = R_w0 @ T[:3, :3] @ sensor.geometry.chip_R[i]
        expected = R_world_chip.T @ independent_dipole(chip_world - source.position_m, source.moment_am2)
        seen = with_source.field_t(address, 0.0) - without.field_t(address, 0.0)
        # 1e-12 T: round-off of fields of a few uT (the two scenes share the magnets' part exactly).
        assert np.allclose(seen, expected, rtol=0, atol=1e-12), (address, seen, expected)
        assert np.linalg.norm(expected) > 5e-6  # large enough for the comparison to mean something


def test_the_moment_follows_its_scale_rows_linearly_and_is_held_at_the_ends():
    source = StraySource(np.array([0.1, 0.0, 0.0]), np.array([0.0, 0.0, 2.0]),
                         np.array([1.0, 2.0, 4.0]), np.array([0.0, 1.0, -0.5]))
    scene = PhysicalScene([SimSensor("s", ADDRS)], stray_sources=[source])
    quiet = PhysicalScene([SimSensor("s", ADDRS)])
    full = PhysicalScene([SimSensor("s", ADDRS)], stray_sources=[StraySource(source.position_m, source.moment_am2)])
    ref = full.field_t(0x0C, 0.0) - quiet.field_t(0x0C, 0.0)
    for t, factor in ((0.0, 0.0), (1.0, 0.0), (1.5, 0.5), (2.0, 1.0), (3.0, 0.25), (4.0, -0.5), (9.0, -0.5)):
        seen = scene.field_t(0x0C, t) - quiet.field_t(0x0C, t)
        assert np.allclose(seen, factor * ref, rtol=0, atol=1e-12), (t, seen, factor * ref)


SCENE = """
version = 1
kind = "sensors"
crosstalk = "off"

[[sensor]]
addresses = [0x0C, 0x0D, 0x0E, 0x0F, 0x10, 0x11, 0x12, 0x13]
centre_m = [0.0, 0.0, 0.01]

[[stray_source]]
position_m = [0.15, 0.0, 0.0]
moment_am2 = [0.0, 0.0, 2.0]
times_s = [0.0, 1.0]
scale = [0.0, 1.0]
"""


def test_a_scene_file_places_stray_sources_and_the_sensor(tmp_path):
    (tmp_path / "a.toml").write_text(SCENE)
    (tmp_path / "b.toml").write_text(SCENE.split("[[stray_source]]")[0])
    scene, free = load_scene(tmp_path / "a.toml"), load_scene(tmp_path / "b.toml")
    assert isinstance(scene, PhysicalScene) and isinstance(free, PhysicalScene)
    assert free.stray_sources == []
    assert np.array_equal(scene.sensors[0].centre_m, [0.0, 0.0, 0.01])
    (source,) = scene.stray_sources
    assert np.array_equal(source.moment_at(0.5), [0.0, 0.0, 1.0])
    # 2 A m^2 at 15 cm, broadside: mu0/(4 pi) m / r^3 = 59 uT at the centre, against -z.
    seen = np.mean([np.linalg.norm(scene.field_t(a, 2.0) - free.field_t(a, 2.0)) for a in ADDRS])
    assert 50e-6 < seen < 70e-6, seen


@pytest.mark.parametrize(("edit", "key", "expected"), [
    (("position_m = [0.15, 0.0, 0.0]", "position_m = [0.0, 0.0, 0.025]"), "stray_source[0].position_m",
     "at least 20 mm from each sensor's centre"),
    (("moment_am2 = [0.0, 0.0, 2.0]", "moment_am2 = [0.0, 2.0]"), "stray_source[0].moment_am2",
     "3 finite numbers (A m^2"),
    (("scale = [0.0, 1.0]\n", ""), "stray_source[0].scale", "times_s and scale given together"),
    (("scale = [0.0, 1.0]", "scale = [0.0]"), "stray_source[0].scale", "2 numbers, one per time"),
    (("times_s = [0.0, 1.0]", "times_s = [1.0, 1.0]"), "stray_source[0].times_s", "strictly increasing"),
    (("moment_am2", "moment"), "stray_source[0].moment", "one of"),
    (("centre_m = [0.0, 0.0, 0.01]", "centre_m = [0.0, 0.01]"), "sensor[0].centre_m", "3 finite numbers (m"),
])
def test_a_bad_stray_source_names_file_key_and_expectation(tmp_path, edit, key, expected):
    path = tmp_path / "bad.toml"
    path.write_text(SCENE.replace(*edit, 1))
    assert_names_file_and_key(load_scene, path, key, expected)
