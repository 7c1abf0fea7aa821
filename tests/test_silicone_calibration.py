"""The silicone's memory at calibration: the load each dwell carried, and the static fits made
on it, so that both estimators' K are the long-term stiffness the daemon's stage expects."""

from __future__ import annotations

import json

import numpy as np

from ftsensord.calibration.dataset import Dataset
from ftsensord.calibration.procedure import calibrate, simulate_dataset
from ftsensord.calibration.relaxation import dwell_loads
from ftsensord.model.viscoelastic import CreepFilter, Relaxation
from ftsensord.sim.loads import StaticLoad, paper_plan
from ftsensord.sim.scene import default_scene

from .conftest import assert_names_file_and_key
from .test_silicone import ADDRESSES, SERIES, _part_with_memory

#: A faster series than the default, so that a short step-and-hold shows both terms.
FAST = Relaxation.from_pairs([[0.10, 0.3], [0.05, 4.0]])


def test_a_dwells_load_is_the_scenes_creep_averaged_over_its_readings():
    # Poses of random loads and dwells on the scene's 1 ms grid: the mean of the scene's own filter
    # (`CreepFilter`, the load held over each step) at each reading must be what dwell_loads gives.
    rng = np.random.default_rng(4)
    n, samples, step = 12, 7, 1e-3
    loads = rng.normal(0.0, 1.0, (n, 6))
    applied = np.cumsum(rng.integers(500, 3000, n))  # grid steps: 0.5-3 s a pose
    first = applied + rng.integers(0, 20, n)
    last = first + rng.integers(1, 60, n) * (
        samples - 1
    )  # readings on the grid, evenly spaced, within the pose
    forward = CreepFilter(SERIES, step)
    want = np.zeros((n, 6))
    k = 0
    for j in range(n):
        w_before = loads[j - 1] if j else np.zeros(6)
        forward.advance(w_before, applied[j] - k)
        k = applied[j]
        for r in np.linspace(first[j], last[j], samples).round().astype(int):
            forward.advance(loads[j], r - k)
            k = r
            want[j] += forward.output(loads[j]) / samples
    got = dwell_loads(SERIES, loads, np.column_stack([applied, first, last]) * step, samples)
    assert np.allclose(got, want, rtol=0, atol=1e-12)  # the same exponentials: round-off
    # A load held long before its readings is carried whole.
    held = dwell_loads(SERIES, loads[:2], np.array([[0.0, 0.0, 0.0], [1.0, 1e4, 1e4 + 1.0]]), samples)
    assert np.allclose(held[1], loads[1], rtol=0, atol=1e-12)


def test_the_nonlinear_estimator_reads_a_long_held_load_after_a_calibration_on_a_creeping_part():
    # The procedure on a part whose silicone creeps: its static fits on the loads the silicone
    # carried over each dwell, so that the nonlinear estimator, exact on a perfect spring, reads a
    # load held for ever as the load (its wrench through the stage's scale). The linear one is
    # not judged here: its own model error at the 200 g poses (5-13 % at this quick
    # calibration's size, creep or none) would hide the creep's.
    ds = simulate_dataset(
        _part_with_memory(FAST),
        "sensor1",
        "six-axis",
        poses=50,  # 10 on each of the plan's five arms
        validation_poses=4,
        samples=10,
        seed=2,
        sweeps=False,
        hold_s=12.0,
        hold_period_s=0.01,
    )
    cal, _ = calibrate(ds)
    found = cal.silicone
    assert found is not None, cal.report["silicone"]
    # 20 %: what the issue asks of the identification, for each fraction and time.
    assert np.allclose(found.relaxation.fractions, FAST.fractions, rtol=0.2), cal.report["silicone"]
    assert np.allclose(found.relaxation.times_s, FAST.times_s, rtol=0.2), cal.report["silicone"]
    # The same part with no memory reads as the creeping one does after a load held for ever.
    held = default_scene()
    nl = cal.nonlinear
    assert nl is not None
    estimator = nl.estimator()

    def read(w: np.ndarray) -> np.ndarray:
        held.set_load("sensor1", StaticLoad(w))
        e = estimator.estimate(np.concatenate([held.field_t(a, 0.0) for a in ADDRESSES]), start=np.eye(4))
        assert e.converged
        return nl.K @ e.xi / found.scale

    loads = np.array([p.wrench() for p, _ in paper_plan("six-axis", n_fit=30, n_validation=0, n_no_load=0)])
    loads = loads[np.linalg.norm(loads[:, :3], axis=1) > 1.0]  # the 200 g poses
    zero = read(np.zeros(6))
    error = np.array([read(w) - zero for w in loads]) - loads
    share = np.sqrt(np.mean(error**2, axis=0) / np.mean(loads**2, axis=0))
    # 2 %: the issue's figure for a held step. Fitted on the dwells' creeping averages as if
    # static (the poses' times dropped, as before 2026-11-26), the same run gives 2.8-3.3 % over
    # seeds 2-5; fitted on the carried loads, 1.4-1.9 % (this quick calibration's noise).
    assert share.mean() < 0.02, share


def test_the_poses_times_survive_the_file_and_a_wrong_order_is_refused(tmp_path):
    ds = simulate_dataset(
        _part_with_memory(SERIES),
        "sensor1",
        "six-axis",
        poses=12,
        validation_poses=2,
        samples=2,
        seed=0,
        sweeps=False,
        no_load_poses=0,
    )
    assert ds.times_s is not None and np.all(np.diff(ds.times_s[:, 0]) > 0)
    ds.save(tmp_path / "ds.json")
    assert np.allclose(Dataset.load(tmp_path / "ds.json").times_s, ds.times_s)
    doc = json.loads((tmp_path / "ds.json").read_text())
    doc["poses"][3]["times_s"][0] = doc["poses"][2]["times_s"][0] - 1.0  # applied before the pose before
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    assert_names_file_and_key(Dataset.load, tmp_path / "bad.json", "times_s", "applied no earlier than")
    del doc["poses"][3]["times_s"]
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    assert_names_file_and_key(Dataset.load, tmp_path / "bad.json", "times_s", "in every pose or in none")


def test_a_load_applied_while_the_pose_before_was_still_read_is_refused(tmp_path):
    # The poses are one after another: a load applied before the last reading of the pose before
    # would put part of that pose's readings under it, which `dwell_loads` cannot know.
    ds = simulate_dataset(
        _part_with_memory(SERIES),
        "sensor1",
        "six-axis",
        poses=6,
        validation_poses=0,
        samples=3,
        seed=0,
        sweeps=False,
        no_load_poses=0,
    )
    assert ds.times_s is not None and np.all(
        ds.times_s[1:, 0] >= ds.times_s[:-1, 2] - 1e-6
    )  # as the rig records them (the check's round-off)
    ds.save(tmp_path / "ds.json")
    doc = json.loads((tmp_path / "ds.json").read_text())
    before = doc["poses"][2]["times_s"]
    doc["poses"][3]["times_s"][0] = (
        before[0] + before[2]
    ) / 2  # after the pose before's load, before its last reading
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    assert_names_file_and_key(Dataset.load, tmp_path / "bad.json", "times_s", "no earlier than")
