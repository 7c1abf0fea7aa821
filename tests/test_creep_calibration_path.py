"""The documented calibration (`ftsensord dataset`, then `calibrate`) of an as-built part whose
silicone creeps, in a room's field: the robot's order (the no-load poses before any load), and
the no-load check's judgement of poses that followed a load (its after-effect named as such; a
rod left on, or a motor near, refused as before)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ftsensord.calibration.calfile import Calibration
from ftsensord.calibration.dataset import Dataset
from ftsensord.calibration.procedure import hold_poses
from ftsensord.calibration.relaxation import settle_s
from ftsensord.calibration.rig import record_dataset, record_hold, simulated_robot
from ftsensord.cli import main
from ftsensord.model.viscoelastic import Relaxation
from ftsensord.sim import load_scene, simulated_bus
from ftsensord.sim.loads import HOLD_PERIOD_S, CalibrationPose, paper_plan
from ftsensord.sim.memory import DEFAULT_RELAXATION
from ftsensord.sim.scene import default_scene_path

#: The paper's Table II (N x3, Nm x3): the 100 g validation's RMSE.
TABLE_II = np.array([0.2338, 0.1136, 0.3775, 4.1e-3, 10.6e-3, 8.5e-3])
#: Where sensor1's tolerances end in the default scene: its silicone goes after.
MARK = "seed = 1                        # this part; another seed is another sensor\n"
#: Today's no-load refusal, which a rod left on and a motor near must keep.
TODAY = "more than 3 flux directions.*not a uniform field alone. Take the rod and mass off.*steel and motors"
#: A motor a few cm from sensor1 (at the world's origin), well inside the distance the docs ask.
MOTOR = "\n[[stray_source]]\nposition_m = [0.0, -0.04, 0.0]\nmoment_am2 = [0.0, 0.0, 2.0]\n"


#: A silicone that creeps more and sooner than the default (the series used before the default
#: was fitted to a published loss): after the loads, its no-load poses carry an after-effect
#: well above the noise floor, where the default's (2.5 % gone within a second, 5 % over 30 s)
#: stays under it at the plan's pace.
HARSH = "relaxation = [[0.10, 1.0], [0.05, 30.0]]\n"


def _scene(tmp_path: Path, seed: int = 53, extra: str = "", silicone: str = "") -> Path:
    """The default scene (the Earth's field: a room) with sensor1 an as-built part of ``seed``
    whose silicone has the default series (or the ``silicone`` table's lines), as a user writes it."""
    text = default_scene_path().read_text()
    assert MARK in text
    path = tmp_path / f"scene-{seed}.toml"
    path.write_text(text.replace(MARK, f"seed = {seed}\n[sensor.silicone]\n{silicone}", 1) + extra)
    return path


def _recorded(scene_path: Path, *, samples: int, hold_s: float, rod_on: bool = False) -> Dataset:
    """A run that does not follow the documented order: the no-load poses after the loaded ones
    (``rod_on``: with a 50 g rod left on for them), then the step-and-hold."""
    scene = load_scene(scene_path)
    sensor = scene.sensors[0]
    bus = simulated_bus(scene, seed=3)
    robot = simulated_robot(scene, sensor.name)
    plan = paper_plan(n_fit=40, n_validation=0, n_no_load=24)
    if rod_on:
        plan = [
            (CalibrationPose(p.gravity_dir, 0.05, np.array([0.0, 0.0, 0.1]), p.rotation), s)
            if s == "no-load"
            else (p, s)
            for p, s in plan
        ]
    late = [p for p in plan if p[1] != "no-load"] + [p for p in plan if p[1] == "no-load"]
    ds = record_dataset(bus, sensor.addresses, late, robot["apply_load"], turn=robot["turn"], samples=samples)
    no_load = ds.split == "no-load"
    ds.wrench[no_load], ds.mass_kg[no_load] = 0.0, 0.0  # as the run's file has them: the rod forgotten
    ds.hold = record_hold(
        bus,
        sensor.addresses,
        hold_poses(),
        robot["apply_load"],
        hold_s=hold_s,
        turn=robot["turn"],
        period_s=HOLD_PERIOD_S,
    )
    return ds


def test_the_two_commands_at_their_defaults_calibrate_a_creeping_part_in_a_room(tmp_path, capsys):
    # A quick run of the documented path: fewer poses, readings and check poses and a shorter hold
    # than the defaults (CI's time); the order, the room check and the identification as they are.
    ds, cal = tmp_path / "ds.json", tmp_path / "cal.json"
    assert (
        main(
            [
                "dataset",
                "--scene",
                str(_scene(tmp_path)),
                "--sensor",
                "sensor1",
                "-o",
                str(ds),
                "--poses",
                "40",
                "--validation-poses",
                "8",
                "--samples",
                "10",
                "--check-poses",
                "3",
                "--hold-s",
                "15",
            ]
        )
        == 0
    )
    data = Dataset.load(ds)
    first = np.argsort(data.times_s[:, 0])[: int(np.sum(data.split == "no-load"))]
    assert (
        np.all(data.split[first] == "no-load") and data.hold is not None
    )  # before any load; the hold recorded
    assert main(["calibrate", str(ds), "-o", str(cal), "--linear-only"]) == 0
    part = Calibration.load(cal)
    assert part.report["room_field"]["source"] == "no-load poses"
    assert part.silicone is not None  # the daemon will undo the creep
    rmse = np.array(list(part.report["validation_rmse"].values()))
    assert np.all(rmse <= TABLE_II), rmse


def test_no_load_poses_after_the_loads_are_refused_naming_the_silicones_after_effect(tmp_path, capsys):
    # 60 readings a pose: the after-effect's extra directions stand above 3x the noise floor (at
    # 10 they hide under it, and the check passes as it should).
    late = _recorded(_scene(tmp_path, silicone=HARSH), samples=60, hold_s=12.0)
    path = tmp_path / "late.json"
    late.save(path)
    assert main(["calibrate", str(path), "-o", str(tmp_path / "cal.json"), "--linear-only"]) == 2
    err = capsys.readouterr().err
    assert "after-effect of the loads before them" in err and "record the no-load poses first" in err
    assert "rod" not in err and "steel" not in err and not (tmp_path / "cal.json").exists()
    need = float(err.split("This silicone needs ")[1].split(" s")[0])
    assert need > 0  # a time from the identified series, not a fixed one
    # Without its step-and-hold the dataset cannot tell creep from a rod: both are said, with the facts.
    doc = json.loads(path.read_text())
    del doc["hold"]
    path.write_text(json.dumps(doc))
    assert main(["calibrate", str(path), "-o", str(tmp_path / "cal.json"), "--linear-only"]) == 2
    err = capsys.readouterr().err
    assert "rod and mass off" in err and "no step-and-hold segment to tell its creep by" in err


def test_a_rod_left_on_is_refused_as_before_on_a_creeping_part_even_after_loads(tmp_path, capsys):
    # The judgement runs (the poses followed loads, the hold gives the series) and the creep it
    # computes does not explain a rod's weight: today's refusal.
    rod = _recorded(_scene(tmp_path, silicone=HARSH), samples=10, hold_s=12.0, rod_on=True)
    rod.save(tmp_path / "rod.json")
    assert (
        main(["calibrate", str(tmp_path / "rod.json"), "-o", str(tmp_path / "cal.json"), "--linear-only"])
        == 2
    )
    err = capsys.readouterr().err
    assert "after-effect" not in err
    assert __import__("re").search(TODAY, err), err


def test_a_motor_near_the_sensor_is_refused_as_before_on_the_documented_path(tmp_path, capsys):
    ds = tmp_path / "ds.json"
    assert (
        main(
            [
                "dataset",
                "--scene",
                str(_scene(tmp_path, extra=MOTOR)),
                "-o",
                str(ds),
                "--poses",
                "40",
                "--validation-poses",
                "0",
                "--samples",
                "10",
                "--check-poses",
                "0",
                "--hold-s",
                "0",
            ]
        )
        == 0
    )
    assert main(["calibrate", str(ds), "-o", str(tmp_path / "cal.json"), "--linear-only"]) == 2
    err = capsys.readouterr().err
    assert __import__("re").search(TODAY, err) and "after-effect" not in err, err


def test_the_settle_time_is_where_the_series_after_effect_falls_to_the_fraction():
    series = Relaxation.from_pairs(DEFAULT_RELAXATION)
    c, rho = series.creep
    for fraction in (1e-2, 1e-3, 1e-4):
        t = settle_s(series, fraction)
        left = lambda s: float(np.sum(c * np.exp(-s / rho)))  # noqa: E731
        # 1e-6 relative: the bisection's resolution is far finer; the after-effect is falling there.
        assert left(t) <= fraction < left(t * (1 - 1e-6))
    assert settle_s(series, 1.0) == 0.0  # the whole after-effect is under a fraction of 1
