"""The physical scene: mechanics, loads, field models, scene files."""

from __future__ import annotations

import numpy as np
import pytest

from ftsensord.model.geometry import SensorGeometry
from ftsensord.model.linear import SENSOR_RANGE
from ftsensord.model.magnet import cylinder_field
from ftsensord.sim import load_scene
from ftsensord.sim.loads import (
    CalibrationPose,
    CalibrationRobotLoad,
    G,
    RecordedLoad,
    StaticLoad,
    StepLoad,
    ramp,
)
from ftsensord.sim.physics import (
    PAPER_STIFFNESS_DIAG,
    PhysicalScene,
    SimSensor,
    two_sensor_scene,
)

from .conftest import assert_names_file_and_key


def test_ring_geometry_follows_the_paper():
    g = SensorGeometry.ring()
    for R in g.chip_R:
        assert np.allclose(R.T @ R, np.eye(3)) and np.linalg.det(R) == pytest.approx(1.0)
        # The chip face (x-y plane) is 25 deg from the shaft: its normal is 65 deg from z.
        assert np.degrees(np.arccos(R[2, 2])) == pytest.approx(65.0)
    assert np.allclose(g.magnet_in_chip(), [0, 0, 6e-3])
    # All magnets at the same height: the near-coplanar set registration must handle.
    assert np.ptp(g.magnet_p[:, 2]) < 1e-15
    assert g.magnet_moment_am2 == pytest.approx(1.81e-3, rel=0.01)


def test_linear_mechanics_is_hookes_law_and_stiffening_stiffens():
    s = SimSensor("s", tuple(range(0x0C, 0x14)))
    w = np.array([10.0, -5.0, 3.0, 0.05, 0.0, -0.1])
    xi = s.deflection(w)
    assert np.allclose(np.diag(PAPER_STIFFNESS_DIAG) @ xi, w)
    stiff = SimSensor("s", tuple(range(0x0C, 0x14)), stiffening=0.3)
    # At the range's deflection the law gives K (xi + 0.3 xi): 30 % stiffer, so it
    # takes 1.3 times the range's wrench to get there.
    full = stiff.deflection(1.3 * SENSOR_RANGE)
    assert np.allclose(full, SENSOR_RANGE / np.array(PAPER_STIFFNESS_DIAG), rtol=1e-9)
    assert np.allclose(stiff.deflection(-1.3 * SENSOR_RANGE), -full)
    assert (
        np.all(np.abs(stiff.deflection(w)) <= np.abs(xi))
        and np.abs(stiff.deflection(w)).sum() < np.abs(xi).sum()
    )


def test_stiffness_must_be_spd():
    with pytest.raises(ValueError, match="positive definite"):
        SimSensor("s", tuple(range(8)), stiffness=np.diag([1, 1, 1, 1, 1, -1.0]))


def test_loads_over_time():
    w1, w2 = np.arange(6.0), -np.arange(6.0)
    assert np.array_equal(StaticLoad(w1).wrench(5.0), w1)
    step = StepLoad(1.0, w1, w2)
    assert np.array_equal(step.wrench(0.999), w1) and np.array_equal(step.wrench(1.0), w2)
    r = ramp(1.0, 3.0, w1, w2)
    assert (
        np.allclose(r.wrench(2.0), 0.0)
        and np.array_equal(r.wrench(0.0), w1)
        and np.array_equal(r.wrench(9), w2)
    )
    with pytest.raises(ValueError):
        RecordedLoad(np.array([0.0, 0.0]), np.zeros((2, 6)))
    with pytest.raises(ValueError):
        StaticLoad(np.array([1.0, np.nan, 0, 0, 0, 0]))


def test_calibration_pose_is_gravity_moved_by_the_adjoint():
    pose = CalibrationPose(np.array([0.0, 0.0, -1.0]), 0.2, np.array([0.1, 0.0, 0.0]))
    w = pose.wrench()
    assert np.allclose(w[:3], [0, 0, -0.2 * G])
    assert np.allclose(w[3:], np.cross([0.1, 0, 0], [0, 0, -0.2 * G]))  # My = +0.196 Nm
    robot = CalibrationRobotLoad(
        [pose, CalibrationPose(np.array([1.0, 0, 0]), 0.05, np.zeros(3))], dwell_s=2.0
    )
    assert np.allclose(robot.wrench(1.9), w) and np.allclose(robot.wrench(2.0)[:3], [0.05 * G, 0, 0])
    assert np.allclose(robot.wrench(100.0)[:3], [0.05 * G, 0, 0])


def test_chip_fields_follow_the_deflection():
    scene = PhysicalScene([SimSensor("s", tuple(range(0x0C, 0x14)))], crosstalk="off")
    rest = scene.field_t(0x0C, 0.0).copy()
    g = SensorGeometry.ring()
    # At rest, crosstalk off: the own magnet's on-axis field, 6 mm behind it.
    on_axis = cylinder_field(np.array([0, 0, -6e-3]), g.magnet_radius_m, g.magnet_length_m, g.magnet_br_t)
    assert rest[2] == pytest.approx(on_axis[2], rel=1e-12) and rest[2] > 0
    assert np.allclose(rest[:2], 0, atol=1e-12)
    # Push the centre piece along +x: chip 0 (on the +x side) closes on its magnet.
    scene.set_load(0, StaticLoad(np.array([10.0, 0, 0, 0, 0, 0])))
    assert scene.field_t(0x0C, 0.0)[2] > 1.5 * rest[2]
    # The opposite chip (index 4, on -x) opens its gap.
    assert scene.field_t(0x10, 0.0)[2] < rest[2]


def test_own_magnet_cylinder_against_dipole_and_crosstalk():
    cyl = PhysicalScene([SimSensor("s", tuple(range(0x0C, 0x14)))], field_model="cylinder", crosstalk="off")
    dip = PhysicalScene([SimSensor("s", tuple(range(0x0C, 0x14)))], field_model="dipole", crosstalk="off")
    both = PhysicalScene(
        [SimSensor("s", tuple(range(0x0C, 0x14)))], field_model="cylinder", crosstalk="dipole"
    )
    diff = np.linalg.norm(cyl.field_t(0x0C, 0) - dip.field_t(0x0C, 0))
    assert 10e-6 < diff < 60e-6  # about 30 uT at the 6 mm gap: more than the chip's noise
    crosstalk = np.linalg.norm(both.field_t(0x0C, 0) - cyl.field_t(0x0C, 0))
    assert crosstalk > 100e-6  # the neighbours matter


def test_temperature_drift_scales_the_field_and_reports_temperature():
    scene = two_sensor_scene(temperature_drift_c_per_s=0.1)
    assert scene.temperature_c(0x0C, 100.0) == pytest.approx(35.0)
    ratio = scene.field_t(0x0C, 100.0)[2] / scene.field_t(0x0C, 0.0)[2]
    assert ratio == pytest.approx(1 - 1.2e-3 * 10)


def test_two_sensors_move_independently():
    scene = two_sensor_scene()
    rest = scene.field_t(0x14, 0.0).copy()
    scene.set_load("sensor1", StaticLoad(np.array([0, 0, 5.0, 0, 0, 0])))
    assert np.array_equal(scene.field_t(0x14, 0.0), rest)
    assert not np.allclose(scene.field_t(0x0C, 0.0), rest)


SENSORS = """\
version = 1
kind = "sensors"
field_model = "cylinder"
crosstalk = "dipole"

[[sensor]]
name = "upper"
addresses = [0x0C, 0x0D, 0x0E, 0x0F, 0x10, 0x11, 0x12, 0x13]
stiffening = 0.2
[sensor.load]
kind = "step"
at_s = 1.0
before = [0, 0, 0, 0, 0, 0]
after = [2.0, 0, 0, 0, 0, 0]

[[sensor]]
addresses = [0x14, 0x15, 0x16, 0x17, 0x18, 0x19, 0x1A, 0x1B]
gap_mm = 5.0
[sensor.load]
kind = "recorded"
times_s = [0.0, 1.0]
wrenches = [[0, 0, 0, 0, 0, 0], [0, 0, -1.0, 0, 0, 0]]
"""


def test_sensors_scene_file(tmp_path):
    path = tmp_path / "s.toml"
    path.write_text(SENSORS)
    scene = load_scene(path)
    assert isinstance(scene, PhysicalScene)
    assert [s.name for s in scene.sensors] == ["upper", "sensor2"]
    assert scene.sensors[0].stiffening == 0.2
    assert np.allclose(scene.sensors[1].geometry.magnet_in_chip(), [0, 0, 5e-3])
    assert np.array_equal(scene.sensors[0].load.wrench(1.5), [2.0, 0, 0, 0, 0, 0])
    assert np.allclose(scene.sensors[1].load.wrench(0.5), [0, 0, -0.5, 0, 0, 0])


@pytest.mark.parametrize(
    ("edit", "key", "expected"),
    [
        (('crosstalk = "dipole"', 'crosstalk = "full"'), "crosstalk", 'one of "off", "dipole", "cylinder"'),
        (("0x12, 0x13]", "0x12]"), "sensor[0].addresses", "8 chip addresses"),
        (("0x1A, 0x1B]", "0x1A, 0x13]"), "sensor[1].addresses", "not used before"),
        (("stiffening = 0.2", "stiffening = -1"), "sensor[0].stiffening", "finite number in [0.0"),
        (("at_s = 1.0", "at = 1.0"), "sensor[0].load.at", "one of"),
        (("after = [2.0, 0, 0, 0, 0, 0]", "after = [2.0, 0, 0]"), "sensor[0].load.after", "6 finite numbers"),
        (("times_s = [0.0, 1.0]", "times_s = [1.0, 0.0]"), "sensor[1].load.times_s", "strictly increasing"),
        (
            ("[[0, 0, 0, 0, 0, 0], [0, 0, -1.0, 0, 0, 0]]", "[[0, 0, 0, 0, 0, 0]]"),
            "sensor[1].load.wrenches",
            "2 rows",
        ),
        (("gap_mm = 5.0", "gap_mm = 0"), "sensor[1].gap_mm", "finite number"),
    ],
)
def test_a_bad_sensors_scene_names_file_key_and_expectation(tmp_path, edit, key, expected):
    path = tmp_path / "bad.toml"
    path.write_text(SENSORS.replace(*edit, 1))
    assert_names_file_and_key(load_scene, path, key, expected)


def test_the_scene_moves_on_its_time_grid():
    scene = two_sensor_scene()
    scene.set_load(0, StepLoad(1.0, np.zeros(6), np.array([3.0, 0, 0, 0, 0, 0])))
    rest, early = scene.field_t(0x0C, 0.0).copy(), scene.field_t(0x0C, 1.0 - 1e-6).copy()
    assert np.array_equal(rest, early)
    loaded = scene.field_t(0x0C, 1.0).copy()
    assert not np.allclose(loaded, rest)
    # Within one 1 ms step every read sees the same deflection.
    assert np.array_equal(scene.field_t(0x0C, 1.0 + 0.9e-3), loaded)


def test_robot_load_in_a_scene_file_and_the_example_config(tmp_path):
    from pathlib import Path

    path = Path(__file__).resolve().parent.parent / "config" / "scene-two-sensors.toml"
    scene = load_scene(path)
    robot = scene.sensors[1].load
    assert isinstance(robot, CalibrationRobotLoad) and len(robot.poses) == 193 and robot.dwell_s == 2.0
    assert not np.allclose(robot.wrench(0.0), robot.wrench(2.0))
    assert np.array_equal(scene.sensors[0].load.wrench(1.5), [2.0, 0, 0, 0, 0, 0])
