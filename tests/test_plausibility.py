"""Plausibility at the door: flux no chip can read, a stiffness that is none, sweeps
that cannot give a position map, saturated chips named, room data that is not a
uniform field, and nonlinear fits that are off refused with their figure."""

from __future__ import annotations

import json

import numpy as np
import pytest

from ftsensord.calibration.calfile import Calibration, checksum
from ftsensord.calibration.dataset import Dataset, Sweep
from ftsensord.calibration.fit import fit
from ftsensord.calibration.nlfit import (
    FIT_ITERATIONS,
    MAGNET_SHIFT_LIMIT_M,
    fit_nonlinear,
    nonlinear_rmse,
)
from ftsensord.calibration.report import write_report
from ftsensord.calibration.rig import record_dataset, simulate_sweeps, simulated_robot
from ftsensord.errors import CalibrationError
from ftsensord.model.geometry import SensorGeometry
from ftsensord.sim import VirtualClock, simulated_bus
from ftsensord.sim.loads import CalibrationPose, paper_plan
from ftsensord.sim.physics import PhysicalScene, SimSensor

from .conftest import assert_names_file_and_key

ADDRS = tuple(range(0x0C, 0x14))
EARTH_T = np.array([22.3, 1.4, -42.6]) * 1e-6


def run(field_t: np.ndarray, plan=None, seed: int = 3) -> Dataset:
    s = SimSensor("s", ADDRS)
    scene = PhysicalScene([s], external_field_t=field_t)
    bus = simulated_bus(scene, clock=VirtualClock(), seed=seed)
    ds = record_dataset(
        bus,
        ADDRS,
        plan or paper_plan(n_fit=60, n_validation=20, n_no_load=12),
        samples=4,
        **simulated_robot(scene, "s"),
    )
    ds.sweeps = simulate_sweeps(ADDRS, SensorGeometry.ring(), samples=4)
    return ds


@pytest.fixture(scope="module")
def clean() -> Dataset:
    return run(np.zeros(3))


@pytest.fixture(scope="module")
def room() -> Dataset:
    return run(EARTH_T)


def copy(ds: Dataset, **changes) -> Dataset:
    return Dataset(**{**ds.__dict__, **changes})


# --- flux a chip cannot read -----------------------------------------------------------------
@pytest.mark.parametrize(
    ("factor", "unit"),
    [(1e3, "written in mT (x 0.001)"), (1e4, "gauss (x 0.0001)"), (1e6, "written in uT (x 1e-06)")],
)
def test_flux_in_the_wrong_unit_is_refused_at_load_naming_the_unit(clean, tmp_path, factor, unit):
    path = tmp_path / "ds.json"
    copy(clean, flux_t=clean.flux_t * factor).save(path)
    assert_names_file_and_key(Dataset.load, path, "poses[0].flux_t", unit)


def test_flux_beyond_the_hall_elements_range_is_refused_by_the_fit_naming_the_chip(clean):
    bad = copy(clean, flux_t=clean.flux_t.copy())
    bad.flux_t[7, 3 * 2 + 1] = 0.0612  # 61 mT on chip 3's y: past the 50 mT the element saturates at
    with pytest.raises(
        CalibrationError, match=r"poses\[7\].flux_t: chip 0x0E \(index 2\) reads 0.0612 on y: .*50 mT"
    ):
        fit(bad)


def test_a_saturated_chips_clipped_values_are_not_judged(clean, tmp_path):
    ds = copy(clean, flux_t=clean.flux_t.copy(), saturated=clean.saturated.copy())
    ds.flux_t[3, 0:3] = 0.07  # whatever a clipped chip reports: left out, not a reading
    ds.saturated[3, 0] = True
    path = tmp_path / "ds.json"
    ds.save(path)
    assert Dataset.load(path).saturated[3, 0]
    assert fit(ds).report["left_out_saturated"] == 1


def test_a_saturated_chip_that_leaves_too_few_poses_is_named(clean):
    ds = copy(clean, saturated=clean.saturated.copy())
    fit_rows = np.flatnonzero(ds.split == "fit")
    ds.saturated[fit_rows[:40], 3] = True
    with pytest.raises(
        CalibrationError, match=r"20 usable fit poses.*40 left out for saturation: chip 0x0F in 40"
    ):
        fit(ds)


# --- a stiffness that is no stiffness ---------------------------------------------------------------
def test_a_k_that_is_not_positive_definite_is_refused_by_the_fit(clean):
    # Wrenches recorded with the wrong sign, gravity too (so the masses agree with them).
    flipped = copy(clean, wrench=-clean.wrench, gravity_dir=-clean.gravity_dir)
    with pytest.raises(
        CalibrationError, match="K is negative definite.*magnets face the other way.*gravity_dir"
    ):
        fit(flipped)
    with pytest.raises(CalibrationError, match=r"the sign of Fx, Fy, Fz, Mx, My, Mz is flipped"):
        fit(copy(clean, wrench=-clean.wrench))  # the masses, lever arms and gravity say otherwise


def test_a_calibration_file_with_a_k_not_positive_definite_names_file_and_key(clean, tmp_path):
    result = fit(clean)
    doc = Calibration(result.model, ADDRS, "SN-1").document()
    doc["K"] = (-np.array(doc["K"])).tolist()  # rank 6 still: only positive definiteness catches it
    doc["checksum"] = checksum(doc)
    path = tmp_path / "cal.json"
    path.write_text(json.dumps(doc))
    assert_names_file_and_key(Calibration.load, path, "K", "positive definite")


def test_a_nonlinear_k_not_positive_definite_is_refused_on_load(clean, tmp_path):
    result = fit(clean)
    doc = Calibration(result.model, ADDRS, "SN-1").document()
    doc["nonlinear"] = {
        "gap_m": 6e-3,
        "ring_radius_m": 8e-3,
        "tilt_deg": 25.0,
        "scale": np.ones((8, 3)).tolist(),
        "offset_t": np.zeros((8, 3)).tolist(),
        "K": np.diag([1e4, 1e4, 1e4, 10, 10, -10.0]).tolist(),
        "zero_twist": [0.0] * 6,
        "fit_rms_residual_t": 1e-6,
    }
    doc["checksum"] = checksum(doc)
    path = tmp_path / "cal.json"
    path.write_text(json.dumps(doc))
    assert_names_file_and_key(Calibration.load, path, "nonlinear.K", "positive definite")


# --- sweeps that cannot give a position map ---------------------------------------------------------
def test_a_rank_deficient_sweep_names_the_chip_and_the_file(clean, tmp_path):
    sweep = clean.sweeps[0x0E]
    along_x = (
        np.abs(sweep.position_m[:, 1] - sweep.position_m[0, 1])
        + np.abs(sweep.position_m[:, 2] - sweep.position_m[0, 2])
        < 1e-12
    )
    flat = copy(clean, sweeps={**clean.sweeps, 0x0E: Sweep(sweep.position_m[along_x], sweep.flux_t[along_x])})
    path = tmp_path / "ds.json"
    flat.save(path)
    with pytest.raises(CalibrationError) as exc:
        fit(Dataset.load(path))
    msg = str(exc.value)
    assert str(path) in msg and "position_sweeps.0x0E" in msg and "position rank < 3" in msg, msg


@pytest.mark.parametrize("bad", [None, 0.001, "[0, 0, 0]"])
def test_a_sweeps_positions_that_are_no_list_are_named_not_its_flux(clean, tmp_path, bad):
    """Before, positions of the wrong kind made the loader ask for a "0 x 3 matrix" of flux_t,
    naming the key that was right."""
    path = tmp_path / "ds.json"
    clean.save(path)
    doc = json.loads(path.read_text())
    doc["position_sweeps"]["0x0E"]["position_m"] = bad
    path.write_text(json.dumps(doc))
    assert_names_file_and_key(Dataset.load, path, "position_sweeps.0x0E.position_m", "positions")


# --- orientations and no-load poses --------------------------------------------------------------------
def test_orientations_round_trip_and_a_wrong_one_names_the_pose(room, tmp_path):
    path = tmp_path / "ds.json"
    room.save(path)
    back = Dataset.load(path)
    assert np.array_equal(back.rotation, room.rotation) and back.path == str(path)
    doc = json.loads(path.read_text())
    doc["poses"][5]["rotation"] = np.eye(3).tolist()  # gravity straight down: not pose 5's
    path.write_text(json.dumps(doc))
    assert_names_file_and_key(Dataset.load, path, "poses[5].rotation", "R^T (0, 0, -1) = gravity_dir")
    del doc["poses"][5]["rotation"]
    path.write_text(json.dumps(doc))
    assert_names_file_and_key(Dataset.load, path, "poses[5].rotation", "in every pose or in none")


def test_no_load_poses_with_the_rod_left_on_are_refused():
    """The rod's weight turns with the sensor: its deflection adds directions no uniform
    field makes, and projecting them out would remove the loads' own signal."""
    plan = paper_plan(n_fit=60, n_validation=0, n_no_load=12)
    rod_on = [
        (CalibrationPose(p.gravity_dir, 0.05, np.array([0.0, 0.0, 0.1]), p.rotation), split)
        if split == "no-load"
        else (p, split)
        for p, split in plan
    ]
    ds = run(EARTH_T, rod_on)
    with pytest.raises(CalibrationError, match="more than 3 flux directions.*rod and mass off"):
        fit(ds)


def test_measuring_the_room_needs_enough_no_load_poses(room):
    few = room.select(
        np.flatnonzero(room.split != "no-load").tolist()
        + np.flatnonzero(room.split == "no-load")[:3].tolist()
    )
    with pytest.raises(CalibrationError, match="3 unsaturated no-load poses.*at least 6"):
        fit(few, room_field="measured")
    # "auto" with too few cannot reject the field, and its own no-load poses show it turning:
    # refused, naming the field and what measuring it needs (not a K bent by it, kept).
    with pytest.raises(CalibrationError, match="cannot be rejected.*turns with the sensor.*at least 6"):
        fit(few)
    with pytest.raises(CalibrationError, match="'none' takes the room as field-free, but the 3 no-load"):
        fit(few, room_field="none")
    assert fit(few, room_field="geometry").report["room_field"]["mode"] == "geometry"


def test_a_field_free_room_with_few_no_load_poses_is_not_taken_for_a_field(clean):
    few = clean.select(
        np.flatnonzero(clean.split != "no-load").tolist()
        + np.flatnonzero(clean.split == "no-load")[:3].tolist()
    )
    assert fit(few).report["room_field"] == {"mode": "none", "no_load_poses": 3}
    assert fit(few, room_field="none").report["room_field"]["mode"] == "none"


# --- the nonlinear fit: progress and refusal ----------------------------------------------------------------
def test_the_nonlinear_fit_reports_progress_and_keeps_a_right_fit(clean):
    steps = []
    cal = fit_nonlinear(clean, progress=steps.append)
    assert [p.step for p in steps] == list(range(1, FIT_ITERATIONS + 1))
    assert all(p.steps == FIT_ITERATIONS for p in steps)
    drawn = SensorGeometry.ring().magnet_p
    assert np.linalg.norm(cal.magnet_p_m - drawn, axis=1).max() < MAGNET_SHIFT_LIMIT_M
    assert steps[-1].rms_residual_t == cal.fit_rms_residual_t <= steps[0].rms_residual_t
    assert steps[-1].elapsed_s >= steps[0].elapsed_s and cal.warnings == ()


def test_the_nonlinear_fit_takes_the_room_field_pose_by_pose(room, clean):
    """The background field is fitted per pose: in the Earth's field the fit is kept, its
    residual as small as in a shielded room's (1.5x: the same noise, three more unknowns
    a pose), and it estimates wrenches as well (the magnets' places are not compared: a
    shift of all of them is a shift of the centre piece, a gauge the fit leaves free)."""
    in_room, shielded = fit_nonlinear(room), fit_nonlinear(clean)
    assert in_room.warnings == ()
    assert in_room.fit_rms_residual_t < 1.5 * shielded.fit_rms_residual_t
    err_room = nonlinear_rmse(in_room, room.select(room.split == "validation"))
    err_clean = nonlinear_rmse(shielded, clean.select(clean.split == "validation"))
    assert np.all(err_room < 1.5 * err_clean + 1e-3), (err_room, err_clean)  # 1 mN/mNm: noise floor


def test_a_calibration_file_keeps_the_fitted_part(clean, tmp_path):
    """Magnet places, moments and the chips' 3 x 3 responses travel through the file."""
    result, nl = fit(clean), fit_nonlinear(clean)
    path = tmp_path / "cal.json"
    Calibration(result.model, ADDRS, "SN-1", nonlinear=nl).save(path)
    back = Calibration.load(path).nonlinear
    for name in ("scale", "offset_t", "K", "magnet_p_m", "magnet_strength"):
        np.testing.assert_array_equal(getattr(back, name), getattr(nl, name))
    doc = json.loads(path.read_text())
    doc["nonlinear"]["magnet_strength"][3] = -1.0
    doc["checksum"] = checksum(doc)
    path.write_text(json.dumps(doc))
    assert_names_file_and_key(Calibration.load, path, "nonlinear.magnet_strength", "over 0")


def test_a_poor_fit_kept_on_request_carries_its_warnings_into_file_and_report(clean, tmp_path):
    """A chip reading 60 uT of garbage on top of its flux: refused (the fit drags magnet 5,
    the one nearest that chip, past the part's tolerance); kept on request, the warning
    travels in the calibration file and heads the report."""
    bad = copy(clean, flux_t=clean.flux_t.copy())
    bad.flux_t[:, 12:15] += np.random.default_rng(0).normal(0, 60e-6, (len(bad), 3))
    with pytest.raises(
        CalibrationError, match=r"refused: magnet 5 was fitted [\d.]+ mm from its drawn place"
    ):
        fit_nonlinear(bad)
    nl = fit_nonlinear(bad, allow_poor_fit=True)
    assert "magnet 5" in nl.warnings[0]
    assert (
        len(nl.warnings) == 2 and "departs from this part" in nl.warnings[1]
    )  # its residual, 60 uT of garbage
    result = fit(clean)
    report = {**result.report, "nonlinear": {"warnings": list(nl.warnings)}}
    path = tmp_path / "cal.json"
    Calibration(result.model, ADDRS, "SN-1", report=report, nonlinear=nl).save(path)
    assert Calibration.load(path).nonlinear.warnings == nl.warnings
    md = tmp_path / "report.md"
    write_report(md, result.model, report, clean.select(clean.split == "validation"), "test")
    text = md.read_text()
    assert "WARNING: the nonlinear calibration was kept against its refusal" in text
    assert "magnet 5 was fitted" in text and "room field: geometry directions projected out" in text
