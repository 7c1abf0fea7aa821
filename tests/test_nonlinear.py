"""The nonlinear estimator at the extremes: full range, cold starts, missing and
saturated chips left out, garbage in. On a dipole scene the forward model is exact,
so the estimate must be too."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ftsensord.model import se3
from ftsensord.model.geometry import SensorGeometry
from ftsensord.model.nonlinear import (
    MAX_RESIDUAL_T,
    STEP_TOL,
    STEP_TOL_RAD,
    WARM_DAMPING,
    FluxModel,
    NonlinearEstimator,
    _normal,
)
from ftsensord.sim.physics import PAPER_STIFFNESS_DIAG, PhysicalScene, SimSensor

G = SensorGeometry.ring()
K = np.diag(PAPER_STIFFNESS_DIAG)
#: The stopping rule's tolerances per component of the twist (m, rad), and the wrench's.
TOL = np.array([STEP_TOL] * 3 + [STEP_TOL_RAD] * 3)
WRENCH_TOL = np.abs(K) @ TOL
SCENE = PhysicalScene([SimSensor("s", tuple(range(0x0C, 0x14)))], field_model="dipole", crosstalk="dipole")


def flux_at(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    xi = np.linalg.solve(K, w)
    return SCENE.chip_fields(G, se3.exp_se3(xi)).ravel(), xi


def estimator() -> NonlinearEstimator:
    return NonlinearEstimator(FluxModel(G, G.magnet_moment_am2, octupole=False), K)


def count_calls(monkeypatch, obj: object, name: str) -> dict[str, int]:
    """Count the calls of ``obj.name`` from now on (they still go through), in ``["calls"]``."""
    counted = {"calls": 0}
    original = getattr(obj, name)

    def counting(*args, **kwargs):  # type: ignore[no-untyped-def]
        counted["calls"] += 1
        return original(*args, **kwargs)

    monkeypatch.setattr(obj, name, counting)
    return counted


def test_forward_model_is_the_dipole_scene():
    T = se3.exp_se3(np.array([1e-3, -5e-4, 3e-4, 0.01, -0.005, 0.008]))
    assert np.allclose(
        FluxModel(G, G.magnet_moment_am2, octupole=False).predict(T),
        SCENE.chip_fields(G, T).ravel(),
        rtol=1e-12,
    )


#: The default physics: each chip's own magnet the exact cylinder, the others dipoles.
CYLINDER = PhysicalScene([SimSensor("s", tuple(range(0x0C, 0x14)))])


@pytest.mark.parametrize(
    "w",
    [
        np.zeros(6),
        np.array([45.0, 0, 12.0, 0, 0.1, 0]),
        np.array([0, -40.0, -15, 0.1, 0, 0]),
        np.array([35.0, -35, 14, 0.14, -0.14, 0.14]),
    ],
)
def test_with_the_octupole_the_model_is_the_cylinder_scene(w):
    """What the model leaves out of the cylinder magnets: at rest (6 mm) the dipole alone is
    29 uT off, with the octupole 0.1 uT (the chips' noise is 2-3 uT a reading); near the
    range's corners (a chip 2-3 mm from its magnet) up to hundreds of uT against a few."""
    T = se3.exp_se3(np.linalg.solve(K, w))
    exact = CYLINDER.chip_fields(G, T).ravel()
    unsaturated = np.repeat(np.all(np.abs(exact.reshape(-1, 3)) < 50e-3, axis=1), 3)
    worst = {
        o: np.abs(FluxModel(G, G.magnet_moment_am2, octupole=o).predict(T) - exact)[unsaturated].max()
        for o in (False, True)
    }
    assert worst[True] < 0.02 * worst[False] and worst[True] < (0.5e-6 if not w.any() else 20e-6), worst


@settings(max_examples=30, deadline=None)
@given(st.tuples(*[st.floats(-3e-3, 3e-3)] * 3, *[st.floats(-0.03, 0.03)] * 3).map(np.array), st.booleans())
def test_analytic_jacobian_matches_finite_differences(xi, octupole):
    model = FluxModel(G, G.magnet_moment_am2, octupole=octupole)
    T = se3.exp_se3(xi)
    _, J = model.predict_and_jacobian(T)
    h = 1e-7  # central differences: error ~h^2 x third derivative, far below 1e-6 here
    for k in range(6):
        d = np.zeros(6)
        d[k] = h
        numeric = (model.predict(se3.exp_se3(d) @ T) - model.predict(se3.exp_se3(-d) @ T)) / (2 * h)
        assert np.allclose(J[:, k], numeric, rtol=1e-5, atol=1e-6 * np.abs(numeric).max())


def test_the_models_kept_constants_follow_its_arrays_changed_in_place():
    """FluxModel keeps what does not change with the pose; a scale or magnet strength
    changed in place (a calibration's iteration may) is seen at the next prediction."""
    g = SensorGeometry(G.chip_R, G.chip_p, G.magnet_p, G.magnet_axis, magnet_strength=np.ones(8))
    model = FluxModel(g, g.magnet_moment_am2, octupole=True)
    T = se3.exp_se3(np.array([1e-4, 0, 0, 0, 0.01, 0]))
    before = model.predict(T)
    model.scale[2] *= 2.0
    doubled = model.predict(T)
    assert np.allclose(doubled[6:9], 2 * before[6:9], rtol=1e-12) and np.array_equal(doubled[:6], before[:6])
    g.strengths[0] *= 1.5  # magnet 0 stronger: every chip's flux changes, chip 0's most
    stronger = model.predict(T)
    change = np.linalg.norm((stronger - doubled).reshape(-1, 3), axis=1)
    assert np.all(change > 0) and np.argmax(change) == 0 and change[0] > 1e-4, change


EXTREMES = [
    np.array(w, float)
    for w in (
        [50, 0, 0, 0, 0, 0],
        [-50, 0, 0, 0, 0, 0],
        [0, 50, 0, 0, 0, 0],
        [0, -50, 0, 0, 0, 0],
        [0, 0, 20, 0, 0, 0],
        [0, 0, -20, 0, 0, 0],
        [0, 0, 0, 0.2, 0, 0],
        [0, 0, 0, 0, -0.2, 0],
        [0, 0, 0, 0, 0, 0.2],
        [35, -35, 14, 0.14, -0.14, 0.14],
    )
]


@pytest.mark.parametrize("w", EXTREMES, ids=lambda w: " ".join(f"{v:g}" for v in w))
def test_full_range_loads_are_recovered_from_a_cold_start(w):
    flux, xi = flux_at(w)
    est = estimator()
    e = est.estimate(flux, start=np.eye(4))
    assert e.converged and e.iterations <= 30
    # Within the stopping rule (Gauss-Newton converges quadratically: usually far within).
    assert np.allclose(e.xi, xi, atol=TOL) and np.allclose(est.wrench(e), w, atol=WRENCH_TOL)


def test_warm_start_follows_a_ramp_in_few_iterations():
    est = estimator()
    iterations = []
    for f in np.linspace(0, 50, 51):
        flux, xi = flux_at(np.array([f, -0.4 * f, 0.2 * f, 0, 0, 0]))
        e = est.estimate(flux)
        assert e.converged and np.allclose(e.xi, xi, atol=TOL)
        iterations.append(e.iterations)
    assert max(iterations[1:]) <= 10  # a cold start at 50 N needs 19


@pytest.mark.parametrize("left_out", [(2,), (0, 1), (3, 7)])
def test_missing_or_saturated_chips_are_left_out(left_out):
    flux, xi = flux_at(np.array([20.0, 10.0, -5.0, 0.05, -0.05, 0.1]))
    usable = np.ones(8, dtype=bool)
    usable[list(left_out)] = False
    for i in left_out:
        flux[3 * i : 3 * i + 3] = [0.05, -0.05, np.nan][:3] if i % 2 else [0.05, 0.05, 0.05]  # junk
    e = estimator().estimate(flux, usable=usable, start=np.eye(4))
    assert e.converged and np.allclose(e.xi, xi, atol=TOL)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_garbage_never_diverges_or_raises(seed):
    rng = np.random.default_rng(seed)
    flux = rng.normal(0, 5e-3, 24)
    e = estimator().estimate(flux, start=np.eye(4))
    assert np.all(np.isfinite(e.pose)) and np.all(np.isfinite(e.xi))
    # It may find some pose, but never one far outside where the magnets are, and never
    # claims one that does not explain the flux.
    assert np.linalg.norm(e.xi[:3]) < 0.05
    assert not e.converged or e.rms_residual_t <= MAX_RESIDUAL_T


def test_a_chip_reading_far_off_is_refused_not_fitted():
    """A chip that reads wrong but is not known to (no error, no saturation) must not
    bend the pose into a wrench that looks right: the residual gives it away."""
    flux, xi = flux_at(np.array([20.0, 0, 0, 0, 0, 0]))
    flux[6:9] = [40e-3, -40e-3, 40e-3]  # chip 3 at a field no magnet of the sensor gives
    e = estimator().estimate(flux, start=np.eye(4))
    assert not e.converged and e.rms_residual_t > MAX_RESIDUAL_T
    usable = np.ones(8, dtype=bool)
    usable[2] = False  # the same chip left out: the rest give the pose
    assert np.allclose(estimator().estimate(flux, usable=usable, start=np.eye(4)).xi, xi, atol=TOL)


def test_nan_or_too_few_channels_is_a_refusal_not_an_exception():
    flux, _ = flux_at(np.zeros(6))
    flux[4] = np.nan
    assert not estimator().estimate(flux).converged
    assert (
        not estimator()
        .estimate(flux_at(np.zeros(6))[0], usable=np.array([1, 0, 0, 0, 0, 0, 0, 0], bool))
        .converged
    )


def test_noise_gives_an_error_the_size_the_jacobian_says():
    rng = np.random.default_rng(4)
    flux, xi = flux_at(np.array([10.0, 0, 0, 0, 0, 0]))
    errs = []
    for _ in range(50):
        e = estimator().estimate(flux + rng.normal(0, 2e-6, 24), start=np.eye(4))
        errs.append(e.xi - xi)
    _, J = FluxModel(G, G.magnet_moment_am2, octupole=False).predict_and_jacobian(se3.exp_se3(xi))
    predicted = np.sqrt(np.diag(np.linalg.inv(J.T @ J))) * 2e-6  # the Cramer-Rao bound at 2 uT
    measured = np.std(errs, axis=0)
    assert np.all(measured < 2 * predicted) and np.all(measured > 0.5 * predicted)


def test_the_45_degree_twin_is_refused_and_the_right_pose_found():
    """Eight identical chips and magnets read the same after a 45 degree turn about the
    ring's axis: a fit that lands on that twin has a perfect residual and a wrench of
    ~8 Nm. It must never be the answer; without a start the estimator finds the real pose."""
    w = np.array([-21.0, 9.0, 20.0, -0.16, 0.14, -0.04])
    flux, xi = flux_at(w)
    twin = se3.exp_se3(np.array([0, 0, 0, 0, 0, np.pi / 4])) @ se3.exp_se3(xi)
    model = FluxModel(G, G.magnet_moment_am2, octupole=False)
    assert np.allclose(model.predict(twin), flux, atol=1e-12)  # the symmetry
    est = estimator()
    at_twin = est.estimate(flux, start=twin)
    assert not at_twin.converged and at_twin.rms_residual_t < 1e-9  # perfect fit, refused
    est.pose = twin  # a warm start gone wrong
    e = est.estimate(flux)
    assert e.converged and np.allclose(est.wrench(e), w, atol=WRENCH_TOL)


def test_a_fit_caught_on_the_twin_from_both_starts_is_turned_back():
    """A model is least right at the range's corners: with the dipole model alone on the
    cylinder magnets, this 46 N load (one chip saturated, left out) ends on the 45 degree
    twin from the rest pose, warm or staged cold; the third start, that answer turned back
    by 45 degrees, finds the load (within the dipole model's own error there)."""
    w = np.array([-45.259, -3.498, 11.649, 0.108, 0.176, 0.02])
    flux = CYLINDER.chip_fields(G, se3.exp_se3(np.linalg.solve(K, w))).ravel()
    usable = np.all(np.abs(flux.reshape(-1, 3)) < 50e-3, axis=1)
    assert usable.sum() == 7
    cold = estimator().estimate(flux, usable, start=np.eye(4))
    assert not cold.converged and abs(cold.xi[5]) > np.pi / 8  # on the twin's side
    est = estimator()
    e = est.estimate(flux, usable)
    assert e.converged and np.allclose(est.wrench(e), w, atol=[0.5, 0.5, 0.5, 0.03, 0.03, 0.03])


def test_kept_jacobians_give_the_fresh_ones_answer_in_two_iterations(monkeypatch):
    """At rest with noise (1 uT a channel, a sample's pose 10 ms from the last), the kept
    Jacobian's chord steps end where new Jacobians every iteration end, within 3 % of the
    estimate's own noise, in two iterations a sample on average and few new Jacobians.
    Measured: 2.5 % at most (the first sample's, from the rest pose), under 0.2 % after;
    the Jacobian's drift within `JACOBIAN_REUSE_M` (3 %) is what moves the end point, and
    3 % of the noise adds 0.05 % to the error's RMS in quadrature."""
    import ftsensord.model.nonlinear as nonlinear

    rng = np.random.default_rng(4)
    flux0, _ = flux_at(np.array([3.0, -2.0, 1.0, 0.01, 0.0, -0.01]))
    samples = [flux0 + rng.normal(0, 1e-6, flux0.shape) for _ in range(60)]
    model = FluxModel(G, G.magnet_moment_am2, octupole=False)
    counted = count_calls(monkeypatch, model, "predict_and_jacobian")
    kept = NonlinearEstimator(model, K, solver="numpy")  # its Python calls are counted
    reused = np.array([kept.estimate(b).xi for b in samples])
    iterations = np.mean([kept.estimate(b).iterations for b in samples])
    jacobians = counted["calls"]
    monkeypatch.setattr(nonlinear, "JACOBIAN_REUSE_M", -1.0)  # never near: a new Jacobian every iteration
    fresh = np.array(
        [estimator().estimate(b, start=se3.exp_se3(x)).xi for b, x in zip(samples, reused, strict=True)]
    )
    scatter = reused.std(axis=0)
    assert np.all(np.abs(reused - fresh).max(axis=0) < 0.03 * scatter), (
        np.abs(reused - fresh).max(axis=0),
        scatter,
    )
    assert iterations <= 2.2 and jacobians < 0.2 * 2 * len(samples)


def test_the_last_steps_flux_from_the_jacobian_ends_where_evaluating_it_does(monkeypatch):
    """At rest with noise, a fit's last step (under `LINEAR_STEP_T` on every channel) takes
    the Jacobian's flux instead of the field's: one field evaluation a sample instead of
    two, and the same end point within 1 % of the estimate's own noise."""
    import ftsensord.model.nonlinear as nonlinear

    rng = np.random.default_rng(5)
    flux0, _ = flux_at(np.array([-4.0, 2.0, 3.0, 0.0, 0.01, 0.01]))
    samples = [flux0 + rng.normal(0, 1e-6, flux0.shape) for _ in range(60)]

    def run() -> tuple[np.ndarray, float]:
        model = FluxModel(G, G.magnet_moment_am2, octupole=False)
        counted = count_calls(monkeypatch, model, "predict")
        est = NonlinearEstimator(model, K, solver="numpy")  # its Python calls are counted
        est.estimate(samples[0])  # the cold start's evaluations are not the ones counted
        counted["calls"] = 0
        xi = np.array([est.estimate(b).xi for b in samples[1:]])
        return xi, counted["calls"] / (len(samples) - 1)

    linear, per_sample = run()
    monkeypatch.setattr(nonlinear, "LINEAR_STEP_T", -1.0)  # every step's flux from the field
    evaluated, per_sample_evaluated = run()
    scatter = evaluated.std(axis=0)
    assert np.all(np.abs(linear - evaluated).max(axis=0) < 0.01 * scatter), (
        np.abs(linear - evaluated).max(axis=0),
        scatter,
    )
    assert per_sample <= 1.1 and per_sample_evaluated >= 1.9, (per_sample, per_sample_evaluated)


@pytest.mark.parametrize("seed", [6, 7, 8, 9, 10])
def test_a_moving_load_is_followed_to_the_same_end_in_fewer_iterations(monkeypatch, seed):
    """A load moving on every axis (40 % of the range, 1.3 Hz, 100 Hz samples, 1 uT of
    noise a channel): the warm start that follows the motion ends within 5 % of the
    estimate's own noise of the exact least-squares pose (new Jacobians every step, tight
    tolerances), in fewer iterations. Measured on seeds 6-10: 2.5-2.8 % with the Jacobian
    reused within 40 um and 4 mrad, 2.1-2.7 % within 20 um and 2 mrad (seed 6 from the last
    pose instead: 1.7 %); 5 % adds 0.1 % to the error's RMS in quadrature, and leaves room
    for another BLAS's round-off to take another path."""
    import ftsensord.model.nonlinear as nonlinear
    from ftsensord.model.linear import SENSOR_RANGE

    rng = np.random.default_rng(seed)
    t = np.arange(80) / 100.0
    loads = 0.4 * SENSOR_RANGE * np.sin(2 * np.pi * 1.3 * t[:, None] + np.arange(6) * np.pi / 3)
    truth = [flux_at(w) for w in loads]
    samples = [b + rng.normal(0, 1e-6, b.shape) for b, _ in truth]

    def run() -> tuple[np.ndarray, float]:
        est = estimator()
        est.estimate(samples[0])  # the cold start is not counted
        fits = [est.estimate(b) for b in samples[1:]]
        assert all(e.converged for e in fits)
        return np.array([e.xi for e in fits]), float(np.mean([e.iterations for e in fits]))

    followed, iterations = run()
    with monkeypatch.context() as m:
        m.setattr(NonlinearEstimator, "_ahead", lambda self, pose: pose)  # from the last pose
        _, iterations_plain = run()
    for name, value in (
        ("JACOBIAN_REUSE_M", -1.0),
        ("LINEAR_STEP_T", -1.0),
        ("STEP_TOL", 1e-12),
        ("STEP_TOL_RAD", 1e-12),
    ):
        monkeypatch.setattr(nonlinear, name, value)  # the exact fit: new Jacobians, every step evaluated
    exact = np.array(
        [estimator().estimate(b, start=se3.exp_se3(x)).xi for b, x in zip(samples[1:], followed)]
    )
    scatter = (exact - np.array([xi for _, xi in truth[1:]])).std(axis=0)  # the noise's part of the error
    assert np.all(np.abs(followed - exact).max(axis=0) < 0.05 * scatter), (
        np.abs(followed - exact).max(axis=0),
        scatter,
    )
    assert iterations < 0.8 * iterations_plain, (iterations, iterations_plain)


def test_a_motion_continued_stays_a_rigid_motion():
    """`se3.continued` moves a pose on by the last motion exactly (constant velocity),
    and 500 continuations in a row stay rotations to round-off (as matrix products they
    drifted off by 1 % within 60 samples)."""
    from ftsensord.model.se3 import continued

    x = np.array([2e-4, -1e-4, 5e-5, 1e-3, -2e-3, 5e-4])
    T0 = se3.exp_se3(np.array([1e-3, 2e-3, -1e-3, 0.01, 0.02, -0.03]))
    T1 = se3.exp_se3(x) @ T0
    ahead, moved, turned = continued(T0, T1)
    assert np.allclose(ahead, se3.exp_se3(x) @ T1, rtol=0, atol=1e-15)
    assert moved == pytest.approx(np.linalg.norm(x[:3])) and turned == pytest.approx(np.linalg.norm(x[3:]))
    before, pose = T0, T1
    for _ in range(500):
        before, pose = pose, continued(before, pose)[0]
    R = pose[:3, :3]
    assert np.abs(R @ R.T - np.eye(3)).max() < 1e-12


# --- the background field and the part as built ---------------------------------------------------------------
def test_an_axial_push_is_not_mistaken_for_a_uniform_field():
    """The ring's one near-degeneracy: 20 N along z reads exactly as 4.5 N in a 1.55 mT field
    along z (the radial flux's slope in z passes through zero near 12 N). Both unknowns at
    once from rest would land there; the staged cold start and the prior do not."""
    w = np.array([0, 0, 20.0, 0, 0, 0])
    flux, xi = flux_at(w)
    e = estimator().estimate(flux, start=np.eye(4))
    assert e.converged and np.allclose(e.xi, xi, atol=TOL) and np.linalg.norm(e.background_t) < 1e-9


@pytest.mark.parametrize("field_ut", [[22.3, 1.4, -42.6], [50.0, 0, 0], [0, 0, 50.0]])
def test_turning_the_sensor_in_a_50_ut_field_gives_no_false_wrench(field_ut):
    """No load, the sensor turned through 48 orientations in a uniform field, tared at the
    first. On the dipole scene the model is exact, so what is left is the prior's pull on
    the field (1 uT against 50 uT: it moves u by under 1e-3 of itself, and the pose by that
    times the pose-field coupling) and the stopping rule: 2 mN and 0.05 mNm bound both with
    margin, 25 and 40 times under the issue's 0.05 N and 2 mNm. Without the background
    term the same sweep gives tenths of a newton."""
    from ftsensord.sim.loads import fibonacci_directions, gravity_to_down

    u_world = np.array(field_ut) * 1e-6
    est, plain = (
        estimator(),
        NonlinearEstimator(FluxModel(G, G.magnet_moment_am2, octupole=False), K, background=False),
    )
    rest = FluxModel(G, G.magnet_moment_am2, octupole=False).predict(np.eye(4))
    worst, worst_plain, xi0, xi0_plain = np.zeros(6), np.zeros(6), None, None
    for k, d in enumerate(fibonacci_directions(48)):
        R = gravity_to_down(d, 2.4 * k)  # R_w0: the sensor's orientation in the world
        flux = rest + np.concatenate([R_i.T @ (R.T @ u_world) for R_i in G.chip_R])
        e, p = est.estimate(flux), plain.estimate(flux)
        assert e.converged
        xi0 = e.xi if xi0 is None else xi0
        xi0_plain = p.xi if xi0_plain is None else xi0_plain
        worst = np.maximum(worst, np.abs(K @ (e.xi - xi0)))
        worst_plain = np.maximum(worst_plain, np.abs(K @ (p.xi - xi0_plain)))
    assert np.all(worst[:3] < 2e-3) and np.all(worst[3:] < 0.05e-3), worst
    assert worst_plain[:3].max() > 0.1  # the term is what rejects it


def test_an_as_built_sensor_in_the_room_is_fitted_to_the_chips_noise():
    """Seed 1's part (config/scene-room.toml's tolerances) calibrated in the Earth's field:
    the fit's free parameters (chip response matrices, magnet positions and moments, a
    background field per pose) absorb the part and the room, so the residual is the
    chips' noise: the median standard error of the pose means, times at most 1.3 (the
    dipole model against the cylinder magnets; the fit's 350 parameters lower it by
    sqrt(1 - 350/1440) = 0.87, noise alone gives 0.87 to 0.9). The old model, per-axis
    scales on the drawn magnets, left 3.4 uT field-free and was refused in the room."""
    from ftsensord.calibration.nlfit import fit_nonlinear
    from ftsensord.calibration.rig import record_dataset, simulated_robot
    from ftsensord.sim import VirtualClock, simulated_bus
    from ftsensord.sim.loads import paper_plan
    from ftsensord.sim.physics import Tolerances

    geometry, gains = Tolerances(0.15e-3, 0.03, np.radians(1.5), 0.02, 0.1e-3, seed=1).build()
    s = SimSensor("s", tuple(range(0x0C, 0x14)), geometry, chip_gain=gains)
    scene = PhysicalScene([s], external_field_t=np.array([22.3, 1.4, -42.6]) * 1e-6)
    ds = record_dataset(
        simulated_bus(scene, clock=VirtualClock(), seed=7),
        s.addresses,
        paper_plan(n_fit=60, n_validation=0, n_no_load=12),
        samples=10,
        **simulated_robot(scene, "s"),
    )
    nl = fit_nonlinear(ds)  # refused if a magnet lands far off or the residual is far above noise
    noise = float(np.median(ds.flux_sem_t))
    assert nl.warnings == () and 0.7 * noise < nl.fit_rms_residual_t < 1.3 * noise
    assert np.max(np.linalg.norm(nl.magnet_p_m - SensorGeometry.ring().magnet_p, axis=1)) < 1e-3


def test_a_calibration_file_says_which_field_model_it_was_fitted_with(tmp_path):
    """The packaged files say "dipole+octupole"; a file without the key was fitted with dipoles
    alone and is evaluated so; any other model names the file and key."""
    import json

    from ftsensord.calibration.calfile import Calibration, checksum
    from ftsensord.config.file import builtin_path

    from .conftest import assert_names_file_and_key

    packaged = Calibration.load(builtin_path("sim-sensor1.json"))
    assert packaged.nonlinear is not None and packaged.nonlinear.octupole
    assert packaged.nonlinear.estimator().model.octupole
    doc = packaged.document()
    path = tmp_path / "old.json"
    for value, octupole in ((None, False), ("dipole", False), ("dipole+octupole", True)):
        if value is None:
            doc["nonlinear"].pop("field_model")
        else:
            doc["nonlinear"]["field_model"] = value
        doc["checksum"] = checksum(doc)
        path.write_text(json.dumps(doc))
        loaded = Calibration.load(path).nonlinear
        assert (
            loaded is not None
            and loaded.octupole == octupole
            and loaded.estimator().model.octupole == octupole
        )
    doc["nonlinear"]["field_model"] = "quadrupole"
    doc["checksum"] = checksum(doc)
    path.write_text(json.dumps(doc))
    assert_names_file_and_key(Calibration.load, path, "nonlinear.field_model", '"dipole+octupole"')


@pytest.mark.parametrize("background", [True, False])
def test_a_jacobian_blind_to_one_axis_is_a_refusal_not_an_exception(background):
    # A warm fit's new Jacobian takes the undamped gains (`UNDAMPED`): their J^T J singular
    # must end the fit as the damped solve's does, not raise out of `estimate`.
    model = FluxModel(G, G.magnet_moment_am2, octupole=False)
    est = NonlinearEstimator(model, K, background=background, solver="numpy")  # its Jacobian is patched
    field = np.zeros(3) if background else None
    assert est.estimate(model.predict(se3.exp_se3(np.linalg.solve(K, [2.0, 0, 0, 0, 0, 0])), field)).converged

    def blind(T, u, with_field):  # the turn about z seen by no chip
        pred, J = FluxModel.predict_and_jacobian(model, T, u, with_field)
        J = J.copy()
        J[:, 5] = 0.0
        return pred, J

    model.predict_and_jacobian = blind
    e = est.estimate(model.predict(se3.exp_se3(np.linalg.solve(K, [6.0, 0, 0, 0, 0, 0])), field))
    assert not e.converged


@pytest.mark.parametrize("background", [True, False])
def test_the_undamped_gains_step_is_the_warm_damped_one(background):
    # `UNDAMPED`: a new Jacobian's step at damping WARM_DAMPING is taken undamped. The two
    # differ by the damping times the scaled J^T J's condition: under 2e-5 of the step on
    # 200 loads to 40 % of range (1.4e-5 the worst measured; "a millionth" it is not).
    model, rng = FluxModel(G, G.magnet_moment_am2, octupole=True), np.random.default_rng(0)
    worst = 0.0
    for _ in range(200):
        w = rng.uniform(-0.4, 0.4, 6) * np.array([10, 10, 20, 0.15, 0.15, 0.1])
        _, J = model.predict_and_jacobian(
            se3.exp_se3(np.linalg.solve(K, w)), np.zeros(3) if background else None, background
        )
        JtJ, Jtr = _normal(J, rng.normal(0, 3e-6, J.shape[0]), np.zeros(3) if background else None)
        damped = JtJ.copy()
        damped.flat[:: damped.shape[0] + 1] *= 1 + WARM_DAMPING
        undamped = np.linalg.solve(JtJ, Jtr)
        worst = max(worst, np.linalg.norm(np.linalg.solve(damped, Jtr) - undamped) / np.linalg.norm(undamped))
    assert worst < 2e-5
