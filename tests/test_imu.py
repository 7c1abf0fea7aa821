"""The MPU-6050 on the sensor's bus: the driver against the emulated chip (registers as the
register map has them, the datasheet's scale), the scene's ``imu`` key, and the guided
calibration reading each pose's gravity with it (the person's seating error measured, a
wrong face caught by the IMU)."""

from __future__ import annotations

import numpy as np
import pytest

from ftsensord.calibration import fixture as fx
from ftsensord.calibration import guided
from ftsensord.chip import mpu6050 as mpu
from ftsensord.errors import ChipNotRespondingError
from ftsensord.sim import load_scene, simulated_bus
from ftsensord.sim.loads import FixedOrientation, gravity_to_down
from ftsensord.sim.person import Person
from ftsensord.sim.scene import default_scene_text

from .conftest import assert_names_file_and_key

ADDRESSES = "addresses = [0x0C, 0x0D, 0x0E, 0x0F, 0x10, 0x11, 0x12, 0x13]\n"


def scene_with(tmp_path, line: str = "imu = 0x68\n"):
    text = default_scene_text()
    assert ADDRESSES in text
    path = tmp_path / "scene.toml"
    path.write_text(text.replace(ADDRESSES, ADDRESSES + line, 1))
    return path


def test_driver_reads_minus_gravity_in_the_sensor_frame(tmp_path):
    scene = load_scene(scene_with(tmp_path))
    bus = simulated_bus(scene, seed=1)
    assert mpu.probe(bus) == 0x68  # a scan finds it; nothing answers at 0x69
    imu = mpu.MPU6050(bus, 0x68)
    assert imu.who_am_i() == mpu.WHO_AM_I_VALUE
    np.testing.assert_array_equal(imu.read_accel_g(), 0.0)  # asleep after power-on: no data
    imu.start()
    device = bus.devices[0x68]
    for gravity in ([0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -0.6, 0.8]):
        g = np.array(gravity) / np.linalg.norm(gravity)
        scene.set_orientation("sensor1", FixedOrientation(gravity_to_down(g, 0.7)))
        mean, sem = imu.mean_accel_g(200)
        # The reading is the specific force, -g, through the part's offset and sensitivity:
        # within the datasheet's tolerances of -g, and at the emulated part's own to the noise.
        assert np.all(
            np.abs(mean + g) <= np.array(mpu.ZERO_G_MG) * 1e-3 + mpu.SENSITIVITY_TOLERANCE + 5 * sem
        )
        np.testing.assert_allclose(mean, -device.sensitivity * g + device.offset_g, atol=5 * sem.max() + 1e-4)
        assert 0.2 * mpu.noise_g() / np.sqrt(200) < sem.max() < 3 * mpu.noise_g() / np.sqrt(200)
    # Another full scale: half the LSB per g, the same reading in g.
    scaled = mpu.MPU6050(bus, 0x68, afs_sel=1)
    scaled.start()
    assert abs(scaled.mean_accel_g(200)[0] - mean).max() < 5 * sem.max() + 2 / 8192


def test_driver_errors_name_the_device(tmp_path):
    bus = simulated_bus(load_scene(scene_with(tmp_path)), seed=1)
    with pytest.raises(ChipNotRespondingError, match="MPU-6050 at 0x69"):
        mpu.MPU6050(bus, 0x69).start()
    with pytest.raises(ValueError, match="0x68 or 0x69"):
        mpu.MPU6050(bus, 0x0C)
    assert mpu.probe(simulated_bus(load_scene(scene_with(tmp_path, "")), seed=1)) is None


def test_scene_imu_key(tmp_path):
    assert load_scene(scene_with(tmp_path)).sensors[0].imu_address == 0x68  # type: ignore[union-attr]
    path = scene_with(tmp_path, "imu = 0x0C\n")
    assert_names_file_and_key(load_scene, path, "imu", "0x68 or 0x69")


class Recording(guided.SimStation):
    """The simulator's person, with gravity's true direction in {0} kept for each try."""

    truth: dict[tuple[int, int], np.ndarray]

    def perform(self, index, attempt, step, reading_at_s, reading_s):
        super().perform(index, attempt, step, reading_at_s, reading_s)
        self.truth = getattr(self, "truth", {})
        R = self.scene.orientation_of(self.sensor, 0.0)
        self.truth[(index, attempt)] = R.T @ np.array([0.0, 0.0, -1.0])


def test_guide_reads_each_pose_gravity_with_the_imu(tmp_path):
    scene = load_scene(scene_with(tmp_path))
    bus = simulated_bus(scene, seed=4)
    fixture = fx.Fixture()
    # Faces seated 2 deg off, a wrong face in 1 step of 8, nothing else.
    person = Person(2.0, 0.0, 0.0, 0.0, 0.0, 0.125, 0.0, 0.0, seed=3)
    station = Recording(scene, "sensor1", fixture, person)
    steps = fx.guided_plan(every=2, no_load=8, validation=6)
    run = guided.GuideRun(steps)
    imu = mpu.MPU6050(bus, 0x68)
    imu.start()
    done = guided.guide(
        run,
        bus=bus,
        addresses=scene.sensors[0].addresses,
        fixture=fixture,
        station=station,
        prompter=_Quiet(),
        samples=30,
        settle_s=0.0,
        save=lambda r: None,
        imu=imu,
    )
    assert done
    faces = [(k, a) for k, a, what in station.slips if what.startswith("face")]
    assert len(faces) >= 2  # the test means something
    for k, a in faces:
        assert a < run.attempts[k] - 1  # refused ...
    assert sum("the IMU reads gravity" in r for r in run.refused) >= len(faces)  # ... by the IMU
    # Each loaded pose's gravity is the one the person made, not the face's: their seating
    # error (2 deg standard deviation: 1.35 deg median) measured to the IMU map's error (its
    # fit on all the faces seated as badly: 0.35 deg median, 0.8 at most, on this run).
    off_face, off_truth = [], []
    for k in [k for k in sorted(run.kept) if steps[k].split != "no-load"]:
        g = run.kept[k].gravity_dir[0]
        off_face.append(np.degrees(np.arccos(np.clip(g @ fixture.normals[steps[k].face - 1], -1, 1))))
        truth = station.truth[(k, run.attempts[k] - 1)]
        off_truth.append(np.degrees(np.arccos(np.clip(g @ truth, -1, 1))))
    assert np.median(off_face) > 1.0
    assert np.median(off_truth) < 0.5 * np.median(off_face), (np.median(off_truth), np.median(off_face))
    assert np.max(off_truth) < 0.5 * np.max(off_face)


class _Quiet:
    def say(self, line: str) -> None:
        pass

    def confirm(self, line: str) -> None:
        pass


def test_guide_command_finds_the_imu(tmp_path, capsys):
    from ftsensord.cli.parser import main

    scene = scene_with(tmp_path)
    args = ["guide", "--scene", str(scene), "--quick", "--yes", "--samples", "10", "--stop-after", "2"]
    assert main([*args, "-o", str(tmp_path / "a.json")]) == 3
    assert "IMU: an MPU-6050 at 0x68 reads each pose's gravity" in capsys.readouterr().out
    assert main([*args, "--no-imu", "-o", str(tmp_path / "b.json")]) == 3
    assert "MPU-6050" not in capsys.readouterr().out
    assert main([*args, "--imu", "0x69", "-o", str(tmp_path / "c.json")]) == 2  # nothing there
    assert "MPU-6050 at 0x69" in capsys.readouterr().err
    assert main([*args, "--imu", "0x0C", "-o", str(tmp_path / "d.json")]) == 2
    assert "--imu: expected 0x68 or 0x69" in capsys.readouterr().err


def test_a_run_with_the_imu_stops_and_resumes(tmp_path, capsys):
    # The IMU's readings are kept in the progress file with the poses: a resumed run fits
    # its map on them and reads every pose's gravity again at the end.
    import json

    from ftsensord.cli.parser import main

    out = tmp_path / "cal.json"
    args = [
        "guide",
        "--scene",
        str(scene_with(tmp_path)),
        "--quick",
        "--yes",
        "--linear-only",
        "--samples",
        "10",
    ]
    assert main([*args, "--stop-after", "12", "-o", str(out)]) == 3
    progress = json.loads((tmp_path / "cal.json.progress.json").read_text())
    assert set(progress["kept"]) <= {int(k) for k in progress["accel"]} and len(progress["kept"]) >= 10
    assert main([*args, "-o", str(out)]) == 0
    assert "resuming:" in capsys.readouterr().out
    progress = json.loads((tmp_path / "cal.json.progress.json").read_text())
    steps = fx.guided_plan(every=2, no_load=8, validation=6)
    assert sorted(progress["kept"]) == list(range(len(steps)))
    assert set(progress["kept"]) <= {int(k) for k in progress["accel"]}
    poses = json.loads(out.read_text())["fit_report"]["guided"]
    assert poses["steps"] == len(steps)
