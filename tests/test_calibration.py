"""Calibration: recovering known K and A, refusing what cannot be identified,
leaving saturated chips out, and the files it reads and writes."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ftsensord.calibration.calfile import Calibration, checksum
from ftsensord.calibration.dataset import Dataset
from ftsensord.calibration.excitation import EXCITATION_TOL, check_excitation
from ftsensord.calibration.fit import (
    fit,
    fit_linear,
    noise_floor,
    rmse,
)
from ftsensord.calibration.rig import record_dataset, simulate_sweeps
from ftsensord.chip import mlx90393 as mlx
from ftsensord.config.file import builtin_path
from ftsensord.errors import CalibrationError, ConfigError
from ftsensord.model import se3
from ftsensord.model.geometry import SensorGeometry
from ftsensord.model.linear import (
    LinearModel,
    PositionMap,
    deflection_twist,
    fit_position_map,
    tip_wrench,
)
from ftsensord.sim import NOISELESS, VirtualClock, simulated_bus, two_sensor_scene
from ftsensord.sim.loads import StaticLoad, paper_plan

from .conftest import assert_names_file_and_key


def synthetic(n: int, rng: np.random.Generator):
    """A known linear sensor: flux B (n, 24), twists Xi = A B, wrenches W = K Xi."""
    K = rng.normal(size=(6, 6)) + 6 * np.eye(6)
    A = rng.normal(size=(6, 24))
    B = rng.normal(size=(n, 24)) * 1e-3
    Xi = B @ A.T
    return K, A, B, Xi, Xi @ K.T


def test_noise_free_data_recovers_k_and_a_to_1e_6():
    K, A, B, Xi, W = synthetic(100, np.random.default_rng(0))
    model = fit_linear(B, Xi, W).model
    assert np.linalg.norm(model.A - A) <= 1e-6 * np.linalg.norm(A)
    assert np.linalg.norm(model.K - K) <= 1e-6 * np.linalg.norm(K)
    assert np.allclose(model.wrench(B), W, rtol=1e-9, atol=1e-12)
    assert np.allclose(model.zero @ model.KA.T, 0.0, atol=1e-12)  # no flux, no load: here b0 maps to 0


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(1e-4, 1e-1))
def test_noisy_wrenches_stay_within_the_bound_the_noise_gives(seed, sigma):
    """With wrench noise N, the fit errs by N Z^+ exactly, Z = [A (B - mean), 1]:
    so |K_hat - K|_F <= |N|_F / sigma_min(Z). A bound, not a statistic: it cannot flake."""
    rng = np.random.default_rng(seed)
    K, A, B, Xi, W = synthetic(80, rng)
    noise = rng.normal(0, sigma, W.shape)
    model = fit_linear(B, Xi, W + noise).model
    Z = np.column_stack([(B - B.mean(0)) @ A.T, np.ones(len(B))])
    bound = np.linalg.norm(noise) / np.linalg.svd(Z, compute_uv=False)[-1]
    assert np.linalg.norm(model.K - K) <= bound * (1 + 1e-9)


def test_noisy_flux_below_the_floor_is_not_inverted():
    """Flux that varies in 6 directions plus noise: the truncated inverse keeps 6."""
    rng = np.random.default_rng(1)
    n, sigma = 200, 1e-6
    basis = rng.normal(size=(6, 24))
    xi = rng.normal(size=(n, 6)) * 1e-3
    B = xi @ basis * 1e-1 + rng.normal(0, sigma, (n, 24))
    K = np.diag([1e4, 1e4, 1e4, 10, 10, 10.0])
    fitted = fit_linear(B, xi, xi @ K.T, floor_t=noise_floor(np.full((n, 24), sigma)))
    assert fitted.flux_rank == 6
    assert np.allclose(fitted.model.K, K, rtol=1e-2)


wrench_sets = st.integers(0, 2**32 - 1)


@settings(deadline=None)  # what is refused is the test, not how fast: a loaded 2-core host took 362 ms
@given(wrench_sets, st.sampled_from(["one-arm", "drop-mz", "tie-fx-fz", "few"]))
def test_rank_deficient_data_is_refused_never_fitted(seed, kind):
    rng = np.random.default_rng(seed)
    W = rng.normal(size=(60, 6)) * np.array([2, 2, 2, 0.1, 0.1, 0.1])
    if kind == "one-arm":
        W = np.array([p.wrench() for p, s in paper_plan("one-arm", n_fit=60) if s == "fit"])
    elif kind == "drop-mz":
        W[:, 5] = 0.3  # constant: no variation
    elif kind == "tie-fx-fz":
        W[:, 2] = 0.5 * W[:, 0] + 1.0
    else:
        W = W[:5]
    e = check_excitation(W)
    assert not e.identifiable and e.describe()
    if kind == "drop-mz":
        assert "Mz is not excited" in e.describe()
    if kind == "tie-fx-fz":
        assert "Fx and Fz always vary together" in e.describe()


def test_one_arm_plan_names_the_tied_axes_and_the_remedy():
    W = np.array([p.wrench() for p, s in paper_plan("one-arm") if s == "fit"])
    e = check_excitation(W)
    assert e.rank == 3
    assert e.describe() == [
        "Mz is not excited",
        "Fx and My always vary together",
        "Fy and Mx always vary together",
    ]
    assert "lever arm points off the shaft axis" in e.advice()
    six = check_excitation(np.array([p.wrench() for p, s in paper_plan("six-axis") if s == "fit"]))
    assert six.identifiable and six.condition < 1 / EXCITATION_TOL


# --- the physical pipeline -------------------------------------------------------------
@pytest.fixture(scope="module")
def small_dataset() -> Dataset:
    scene = two_sensor_scene()
    bus = simulated_bus(scene, clock=VirtualClock(), seed=3)
    addrs = scene.sensors[0].addresses
    ds = record_dataset(
        bus,
        addrs,
        paper_plan("six-axis", n_fit=60, n_validation=20),
        lambda w: scene.set_load(0, StaticLoad(w)),
        samples=4,
        serial="sim-1",
    )
    ds.sweeps = simulate_sweeps(addrs, SensorGeometry.ring(), samples=4)
    return ds


def test_calibration_of_the_simulated_sensor_validates_well(small_dataset):
    result = fit(small_dataset)
    report = result.report
    assert report["fit_poses"] == 60 and report["validation_poses"] == 20
    val = np.array(list(report["validation_rmse"].values()))
    # Loads are at most ~2 N and ~0.2 Nm: a working calibration errs by a few percent of them.
    assert np.all(val[:3] < 0.2) and np.all(val[3:] < 0.01)
    assert 0.2 < report["isotropy"]["forces"] <= 1 and 0.2 < report["isotropy"]["torques"] <= 1


@settings(max_examples=15, deadline=None)
@given(st.sets(st.integers(0, 59), min_size=1, max_size=8), st.integers(0, 7), st.floats(-0.07, 0.07))
def test_saturated_chips_are_flagged_and_their_poses_not_used(small_dataset, rows, chip, junk):
    ds = small_dataset
    tainted = Dataset(**{**ds.__dict__, "flux_t": ds.flux_t.copy(), "saturated": ds.saturated.copy()})
    fit_rows = np.flatnonzero(ds.split == "fit")[sorted(rows)]
    tainted.saturated[fit_rows, chip] = True
    tainted.flux_t[fit_rows, 3 * chip : 3 * chip + 3] = junk  # whatever a clipped chip reports
    result = fit(tainted)
    assert result.report["left_out_saturated"] == len(rows)
    clean = fit(ds.select(~np.isin(np.arange(len(ds)), fit_rows)))
    assert np.allclose(result.model.KA, clean.model.KA, rtol=1e-12, atol=0)


def test_recording_flags_a_saturated_chip():
    scene = two_sensor_scene()
    bus = simulated_bus(scene, clock=VirtualClock(), noise=NOISELESS)
    # GAIN_SEL 7, RES 0 spans +-4.9 mT on X/Y; 30 N along x gives chip 0 (on +x) By = 6 mT.
    narrow = mlx.Settings(gain_sel=7, res_x=0, res_y=0, res_z=0)
    ds = record_dataset(
        bus,
        scene.sensors[0].addresses,
        [(p, "fit") for p, _ in paper_plan("six-axis", n_fit=1, n_validation=0)],
        lambda w: scene.set_load(0, StaticLoad(np.array([30.0, 0, 0, 0, 0, 0]))),
        settings=narrow,
        samples=2,
    )
    assert ds.saturated[0, 0] and not ds.saturated[0].all()


def test_refused_dataset_says_so(small_dataset):
    ds = small_dataset
    # Loads from a fixture that records no masses (so no mass-given wrench to check them by).
    one_arm = Dataset(**{**ds.__dict__, "wrench": ds.wrench.copy(), "mass_kg": np.zeros(len(ds))})
    one_arm.wrench[:, 5] = 0.0
    with pytest.raises(CalibrationError, match="Mz is not excited"):
        fit(one_arm)
    with pytest.raises(CalibrationError, match="at least 26"):
        fit(ds.select(np.arange(len(ds)) < 20))


def test_twist_from_flux_recovers_the_deflection_of_a_noiseless_sensor():
    scene = two_sensor_scene(crosstalk="off")
    g = scene.sensors[0].geometry
    sweeps = simulate_sweeps(range(8), g, noise=NOISELESS, span_m=0.2e-3)
    fits = [fit_position_map(sweeps[i].flux_t, sweeps[i].position_m) for i in range(8)]
    pmap = PositionMap(np.array([f[0] for f in fits]), np.array([f[1] for f in fits]))
    w = np.array([0.5, -0.3, 0.4, 0.0, 0.0, 0.0])
    truth = scene.sensors[0].deflection(w)
    flux = scene.chip_fields(g, se3.exp_se3(truth))
    xi = deflection_twist(flux, g, pmap)
    # Eq. 1 is linear, the field is not (B_x ~ x z / r^5 couples the axes): a small
    # translation comes back within 3 %, with a spurious rotation whose displacement at
    # the magnet ring (13.4 mm) stays within 5 % of the translation.
    assert np.linalg.norm(xi[:3] - truth[:3]) <= 0.03 * np.linalg.norm(truth[:3])
    assert np.linalg.norm(xi[3:]) * 0.0134 <= 0.05 * np.linalg.norm(truth[:3])


def test_tip_wrench_of_two_sensors():
    w1, w2 = np.array([1.0, 0, 0, 0, 0, 0]), np.array([0, 2.0, 0, 0, 0, 0.01])
    p1, p2 = np.array([0, 0, 0.2]), np.array([0, 0, 0.1])
    w = tip_wrench([w1, w2], [se3.pose(p=p1), se3.pose(p=p2)])
    assert np.allclose(w[:3], [1, 2, 0])
    assert np.allclose(w[3:], np.cross(p1, w1[:3]) + np.cross(p2, w2[:3]) + [0, 0, 0.01])


# --- files -----------------------------------------------------------------------------------
def test_dataset_round_trips_and_bad_files_name_the_key(small_dataset, tmp_path):
    path = tmp_path / "ds.json"
    small_dataset.save(path)
    back = Dataset.load(path)
    assert np.array_equal(back.flux_t, small_dataset.flux_t) and back.addresses == small_dataset.addresses
    assert np.array_equal(back.sweeps[0x0C].flux_t, small_dataset.sweeps[0x0C].flux_t)
    doc = json.loads(path.read_text())
    doc["poses"][4]["flux_t"] = doc["poses"][4]["flux_t"][:10]
    path.write_text(json.dumps(doc))
    with pytest.raises(ConfigError, match=r"ds.json: poses\[4\].flux_t: expected 24 finite numbers"):
        Dataset.load(path)


def calibration(result, ds) -> Calibration:
    return Calibration(
        result.model,
        ds.addresses,
        "SN-7",
        "sensor1",
        result.position_map,
        result.report,
        wrench_range=result.wrench_range,
    )


def test_calibration_file_round_trips(small_dataset, tmp_path):
    result = fit(small_dataset)
    path = tmp_path / "cal.json"
    calibration(result, small_dataset).save(path)
    cal = Calibration.load(path)
    assert np.array_equal(cal.model.KA, result.model.KA) and np.array_equal(cal.model.zero, result.model.zero)
    assert cal.serial == "SN-7" and cal.frame == "sensor1" and cal.addresses == tuple(range(0x0C, 0x14))
    assert np.array_equal(rmse(cal.model, small_dataset), rmse(result.model, small_dataset))
    fitted = small_dataset.select(small_dataset.split == "fit")
    assert np.array_equal(cal.wrench_range, np.abs(fitted.wrench).max(axis=0))


@pytest.mark.parametrize(
    ("change", "key", "expected"),
    [
        (lambda d: d.update(version=2), "version", "1 (this ftsensord reads version 1)"),
        (lambda d: d["K"][2].__setitem__(3, float("nan")), "K", "6 x 6 matrix of finite numbers"),
        (lambda d: d["A"].pop(), "A", "6 x 24 matrix"),
        (lambda d: d["units"].update(zero_flux="uT"), "units", "expected"),
        (lambda d: d["sensor"]["addresses"].__setitem__(1, "0x0C"), "sensor.addresses", "not used twice"),
        (lambda d: d["sensor"]["addresses"].__setitem__(0, "0x40"), "sensor.addresses[0]", "0x0C-0x1B"),
        (lambda d: d.update(colour="red"), "colour", "one of"),
        (lambda d: d["zero_flux"].__setitem__(0, 1.0), "checksum", "changed after it was written"),
        (lambda d: d.pop("checksum"), "checksum", "missing"),
        (lambda d: d["wrench_range"].pop(), "wrench_range", "6 finite numbers (N, Nm)"),
        (lambda d: d["wrench_range"].__setitem__(2, 0.0), "wrench_range", "6 numbers over 0"),
        # NaN or Infinity in a part no parser reads (json.loads takes them): before, the checksum's
        # canonical JSON raised a bare "Out of range float values are not JSON compliant".
        (lambda d: d["fit_report"].update(note=float("nan")), "fit_report.note", "finite numbers"),
        (lambda d: d["sensor"].update(serial=float("inf")), "sensor.serial", "finite numbers"),
    ],
)
def test_a_bad_calibration_file_names_the_file_and_key(small_dataset, tmp_path, change, key, expected):
    path = tmp_path / "cal.json"
    doc = calibration(fit(small_dataset), small_dataset).document()
    change(doc)
    path.write_text(json.dumps(doc))
    assert_names_file_and_key(Calibration.load, path, key, expected)


def test_a_file_written_before_wrench_range_still_loads_without_one(small_dataset, tmp_path):
    doc = calibration(fit(small_dataset), small_dataset).document()
    del doc["wrench_range"]
    doc["checksum"] = checksum(doc)
    path = tmp_path / "cal.json"
    path.write_text(json.dumps(doc))
    assert Calibration.load(path).wrench_range is None


def test_a_rank_deficient_k_a_is_refused_even_with_a_valid_checksum(small_dataset, tmp_path):
    doc = calibration(fit(small_dataset), small_dataset).document()
    doc["K"][5] = [0.0] * 6
    doc["checksum"] = checksum(doc)
    path = tmp_path / "cal.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(ConfigError, match="K A of rank 6"):
        Calibration.load(path)


def test_linear_model_with_zero_and_batches():
    rng = np.random.default_rng(2)
    m = LinearModel(np.eye(6), rng.normal(size=(6, 24)), rng.normal(size=24))
    b = rng.normal(size=(5, 24))
    assert np.allclose(m.wrench(b), (b - m.zero) @ (m.K @ m.A).T)
    assert np.allclose(m.with_zero(b[0]).wrench(b[0]), 0.0)


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from(["drop-mz", "tie-mx-fy", "constant"]))
def test_fit_refuses_rank_deficient_data_rather_than_returning_a_matrix(seed, kind):
    rng = np.random.default_rng(seed)
    n = 40
    W = rng.normal(size=(n, 6)) * np.array([2, 2, 2, 0.1, 0.1, 0.1])
    if kind == "drop-mz":
        W[:, 5] = 0.0
    elif kind == "tie-mx-fy":
        W[:, 3] = -0.1 * W[:, 1]
    else:
        W[:] = W[0]
    ds = Dataset(
        (*range(0x0C, 0x14),),
        W,
        rng.normal(size=(n, 24)) * 1e-3,
        np.full((n, 24), 1e-7),
        np.zeros((n, 8), dtype=bool),
        np.array(["fit"] * n),
        np.zeros(n),
        np.zeros((n, 3)),
        np.zeros((n, 3)),
        samples_per_pose=10,
    )
    with pytest.raises(CalibrationError, match="not identifiable"):
        fit(ds)


@pytest.mark.parametrize("key", ["K", "nonlinear.K"])
def test_a_stiffness_at_the_end_of_the_float_range_is_refused_naming_it(tmp_path, key):
    """An entry of -1e308 (finite, so it passes the matrix's own check) with the checksum made
    again: before, the eigenvalues of nonlinear.K's symmetric part overflowed and a bare
    LinAlgError ("Eigenvalues did not converge") left the loader, naming neither file nor key."""
    doc = Calibration.load(builtin_path("sim-sensor1.json")).document()
    (doc["nonlinear"]["K"] if key == "nonlinear.K" else doc["K"])[1][1] = -1e308
    doc["checksum"] = checksum(doc)
    path = tmp_path / "cal.json"
    path.write_text(json.dumps(doc))
    assert_names_file_and_key(Calibration.load, path, key, "expected")


def test_a_bad_chip_position_map_is_named_by_its_index(tmp_path):
    """position_map.M[5], not position_map.M[5]M: the item's key joined to its list's."""
    doc = json.loads(builtin_path("sim-sensor1.json").read_text())
    doc["position_map"]["M"][5] = [[1, 2], [3, 4]]
    doc["checksum"] = checksum(doc)
    path = tmp_path / "cal.json"
    path.write_text(json.dumps(doc))
    assert_names_file_and_key(Calibration.load, path, "position_map.M[5]: ", "a 3 x 3 matrix")
