"""Each wrench sample's sigma: against a Monte Carlo of the simulated chips' noise, through
the filter, in degraded mode, on the wire and in the client."""

from __future__ import annotations

import json
import math
import os
import time
import uuid
from dataclasses import replace

import numpy as np
import pytest
import zmq

from ftsensord.calibration.calfile import Calibration, checksum
from ftsensord.calibration.fit import error_model
from ftsensord.calibration.procedure import calibrate
from ftsensord.chip import mlx90393 as mlx
from ftsensord.client import Subscriber
from ftsensord.config.file import builtin_path
from ftsensord.model import se3
from ftsensord.model.linear import SENSOR_RANGE
from ftsensord.model.nonlinear import JACOBIAN_REUSE_M, PRIOR_WEIGHT
from ftsensord.processing.filters import WrenchFilter, variance_factors
from ftsensord.processing.pipeline import channel_sigma_t
from ftsensord.processing.tare import carry_tares, tare_on
from ftsensord.processing.uncertainty import (
    AXES,
    NOISE_SIGMAS,
    SPREAD_SAMPLES,
    ModelError,
    Uncertainty,
    propagate,
    undithered,
)
from ftsensord.protocol import wire
from ftsensord.sim import two_sensor_scene
from ftsensord.sim.loads import StaticLoad

from .test_calibration import small_dataset  # noqa: F401 (a fixture)
from .test_daemon import Rig

EVERY = np.ones(8, dtype=bool)


@pytest.fixture
def quiet_rig(tmp_path):
    r = Rig(tmp_path, "temperature_every = 0")  # no temperature stage: the wrench is K A's alone
    yield r
    r.close()


def test_the_sigmas_noise_part_is_the_simulated_chips_noise_through_k_a(quiet_rig):
    """1500 cycles at a held load on the simulator's noisy chips: each axis's spread against
    the noise part of the published sigma (the chips' datasheet noise through K A)."""
    out = quiet_rig.cycles(1500)
    wrench = np.array([s.values for s in out["wrench/sensor1"]])
    sigma = np.array([s.values for s in out["sigma/wrench/sensor1"]])
    assert [s.seq for s in out["sigma/wrench/sensor1"]] == [s.seq for s in out["wrench/sensor1"]]
    p = quiet_rig.daemon.sensors[0]
    noise = np.sqrt(p.uncertainty.maps(p.version, "linear", EVERY, None)[1])
    measured = wrench.std(axis=0)
    # 15 %: the simulated chips' noise is the emulator's own, not the datasheet's table that
    # channel_sigma_t reads; the spread at a held load is the noise's independent part (the
    # quantisation's undithered part is the same at every sample); the spread's own error over
    # 1500 samples is 2 % (1 / sqrt(2 n)).
    assert measured == pytest.approx(noise, rel=0.15)
    # The published sigma adds the calibration's model error at the sample's load (the packaged
    # file's, read through its flux model), the load taken NOISE_SIGMAS of noise towards zero,
    # and untared the undithered quantisation, q^2 a channel through K A: sqrt(noise^2 + model +
    # quantisation) at every sample, to float32-free round-off (untared, unfiltered).
    u = p.uncertainty
    m = u.linear_error
    assert m.source == "flux model" and not p.tared
    model = m.variance(wrench[-1], p.tare_wrench, False, NOISE_SIGMAS * noise)
    quantisation = (p.model.KA**2) @ u.bias_t**2
    assert np.all(model > 0) and np.all(quantisation > 0)
    assert sigma[-1] == pytest.approx(np.sqrt(noise**2 + model + quantisation), rel=1e-12)


def test_a_chip_left_out_widens_the_sigma_and_no_estimate_has_none(quiet_rig):
    p = quiet_rig.daemon.sensors[0]
    u = p.uncertainty
    full = u.maps(p.version, "linear", EVERY, None)[1]
    for lost in ([3], [0, 5]):
        left = EVERY.copy()
        left[lost] = False
        degraded = u.maps(p.version, "linear", left, None)[1]
        assert np.all(degraded > full), f"chips {lost} out"
    s = u.sample(p.version, "linear", EVERY, np.full(6, np.nan), p.tare_wrench, False, None, 1.0)
    assert np.all(np.isnan(s.sigma)) and np.all(np.isnan(s.covariance()))


def test_the_tares_noise_enters_as_an_offset_the_filter_does_not_shrink(quiet_rig):
    p = quiet_rig.daemon.sensors[0]
    quiet_rig.cycles(2)
    p.tare(p.model.zero, None, 4)
    noise, diag, offset = p.uncertainty.maps(p.version, "linear", EVERY, 4)
    assert np.allclose(offset, noise / 4)
    s = p.uncertainty.sample(p.version, "linear", EVERY, np.zeros(6), p.tare_wrench, True, 4, 0.01)
    # Noise x the filter's factor, the tare's noise whole, and (this packaged file records its
    # validation RMS only) that RMS at every load; at the tare's load no quantisation (its bias
    # there is the tare's own); 1e-12: round-off.
    rmse = p.uncertainty.linear_error.rest
    assert s.sigma == pytest.approx(np.sqrt(0.01 * diag + diag / 4 + rmse**2), rel=1e-12)


@pytest.mark.parametrize(
    ("averaging", "lowpass_hz"),
    [(1, 0.0), (4, 0.0), (1, 5.0), (5, 3.0), (20, 1.0)],
)
def test_the_filters_variance_factor_against_a_monte_carlo(averaging, lowpass_hz):
    """20000 runs of white noise through the filter: the variance of each of its first 60
    outputs after a reset against `variance_factor` at that output."""
    rng = np.random.default_rng(3811)
    runs, steps = 20000, 60
    x = rng.standard_normal((steps, runs))
    f = WrenchFilter(averaging, lowpass_hz, 100.0)
    predicted, outputs = [], []
    for k in range(steps):
        y, _ = f.update(x[k], 0)  # each run a column: the filter is linear and acts per column
        outputs.append(np.array(y))
        predicted.append(f.variance_factor())
    measured = np.var(outputs, axis=1)
    # 5 %: a variance over 20000 draws has a relative error of sqrt(2 / 20000) = 1 %; 5 sigma.
    assert measured == pytest.approx(predicted, rel=0.05)
    if lowpass_hz == 0.0:
        assert predicted[-1] == pytest.approx(1 / averaging)
    elif averaging == 1:
        a = math.exp(-2 * math.pi * lowpass_hz / 100.0)
        assert predicted[-1] == pytest.approx((1 - a) / (1 + a), rel=1e-6)  # 1e-6: the table's settling


def brute_force_factors(averaging: int, alpha: float, steps: int) -> np.ndarray:
    """The filter's weights on each input, built output by output, and their squares' sums."""
    w = np.zeros(steps)
    out = []
    for k in range(1, steps + 1):
        n = min(k, averaging)
        a = np.zeros(steps)
        a[k - n : k] = 1.0 / n
        w = a if k == 1 else (1 - alpha) * w + alpha * a
        out.append(float(w @ w))
    return np.array(out)


@pytest.mark.parametrize(
    ("averaging", "lowpass_hz", "rate_hz"),
    [
        (1, 5.0, 100.0),
        (2, 5.0, 100.0),
        (4, 0.05, 1000.0),
        (7, 3.0, 100.0),
        (25, 1.0, 100.0),
        (10, 0.0, 100.0),
    ],
)
def test_the_variance_factors_closed_form_is_the_brute_force_sum(averaging, lowpass_hz, rate_hz):
    """Every output from the first to well past the start-up (2 x averaging + 600), against the
    weights' squares summed one by one; then the steady factor against a long run's end."""
    alpha = 1.0 if lowpass_hz == 0 else 1 - math.exp(-2 * math.pi * lowpass_hz / rate_hz)
    f = variance_factors(averaging, alpha)
    steps = 2 * averaging + 600
    brute = brute_force_factors(averaging, alpha, steps)
    closed = np.array([f.at(n) for n in range(1, steps + 1)])
    assert closed == pytest.approx(brute, rel=1e-12)  # 1e-12: round-off of a few thousand sums
    if alpha < 1:
        settled = 1 + math.ceil(40 / alpha)  # b^(2k) = exp(-2 alpha k): under 1e-30 of the start by then
        assert f.at(settled) == pytest.approx(f.steady, rel=1e-12)
        w_steady = np.array([(1 - (1 - alpha) ** (d + 1)) / averaging for d in range(averaging)])
        lags = np.arange(averaging, averaging + settled)
        far = (1 - alpha) ** (lags - averaging + 1) * (1 - (1 - alpha) ** averaging) / averaging
        assert f.steady == pytest.approx(float(w_steady @ w_steady + far @ far), rel=1e-9)


def test_the_variance_factors_limits():
    """The points where the formula's parts are singular or end: no low-pass (alpha = 1), no
    averaging (the low-pass's own (1 - a)/(1 + a)), a cutoff -> 0 (alpha -> 0: the steady factor
    -> alpha / 2, which the formula loses nothing of to cancellation), one input (factor 1)."""
    assert variance_factors(1, 1.0).at(1) == 1.0 and variance_factors(1, 1.0).at(10**6) == 1.0
    assert variance_factors(8, 1.0).steady == pytest.approx(1 / 8) and variance_factors(8, 1.0).at(
        3
    ) == pytest.approx(1 / 3)
    a = math.exp(-2 * math.pi * 2.0 / 100)
    assert variance_factors(1, 1 - a).steady == pytest.approx((1 - a) / (1 + a), rel=1e-14)
    for averaging in (1, 5, 10000):
        for alpha in (1e-6, 1e-9, 1e-12):
            f = variance_factors(averaging, alpha)
            assert f.at(1) == 1.0
            # alpha / 2 (1 + O(N alpha)): the window's own terms are (N alpha)^2 / 3 N of it.
            assert f.steady == pytest.approx(alpha / 2, rel=averaging * alpha + 1e-9)
            assert all(0 < f.at(n) <= 1 for n in (2, averaging, 2 * averaging + 1, 10**12))
    # The largest averaging the configuration takes, with the slowest low-pass: the start-up's
    # 2N steps, not the low-pass's millions; its factors still fall from 1 to the steady one.
    f = variance_factors(10000, 1 - math.exp(-2 * math.pi * 0.01 / 1000))
    assert len(f.head) == 20000 and 1 > f.at(10000) > f.at(20000) > f.at(50000) > f.steady
    assert f.at(10**9) == pytest.approx(f.steady, rel=1e-12)


def test_the_model_error_is_fitted_against_the_load_and_read_back():
    """Errors drawn with a known spread per axis, rest^2 + sum_j (G_kj w_j)^2: the fit gives back
    G's entries, and the sigma its variance at a load."""
    rng = np.random.default_rng(3812)
    span = np.array([10, 10, 5, 0.05, 0.05, 0.05])
    wrench = rng.uniform(-1, 1, (4000, 6)) * span
    G = np.zeros((6, 6))
    # a gain, two cross-talks and a torque's gain, each as large as the rest at its axis's span
    G[1, 1], G[1, 3], G[0, 4], G[5, 5] = 0.1, 20.0, 0.4, 0.02
    rest = np.array([0.01, 0.01, 0.02, 0.001, 0.001, 0.001])
    spread = np.sqrt(rest**2 + (wrench**2) @ (G**2).T)
    error = rng.standard_normal((4000, 6)) * spread
    fitted = error_model(error, wrench)
    assert fitted is not None and fitted["loads"] == 4000 and fitted["source"] == "poses"
    m = ModelError.from_report({"error_model": fitted})
    assert m.source == "poses"
    # The variance it gives against the one drawn, over loads of the same span: each of the
    # form's terms shares the spread with the others (a gain's square is partly a spread and
    # a curvature term), so the check is the sum. 10 %: the fit's 25 coefficients from 4000
    # noisy squares (each square's relative spread sqrt(2)), a few % each.
    test = rng.uniform(-1, 1, (500, 6)) * span
    drawn = rest**2 + (test**2) @ (G**2).T
    fitted_var = np.array([m.variance(w, np.zeros(6), tared=False) for w in test])
    assert np.mean(fitted_var, axis=0) == pytest.approx(np.mean(drawn, axis=0), rel=0.1)
    # and at each drawn term's own load, where the variance is that term's alone (20 %: one load).
    for k, j in [(1, 1), (1, 3), (0, 4), (5, 5)]:
        at = np.zeros(6)
        at[j] = span[j]
        assert m.variance(at, np.zeros(6), False)[k] == pytest.approx(
            rest[k] ** 2 + (G[k, j] * span[j]) ** 2, rel=0.2
        )
    at_rest_tared = m.variance(np.zeros(6), np.zeros(6), tared=True)
    assert np.all(at_rest_tared == 0)  # at the tare's own load: nothing of the model's error left
    assert np.allclose(m.variance(np.zeros(6), np.zeros(6), tared=False), m.rest**2)
    assert ModelError.from_report({}).source == "none"
    assert error_model(error[:12], wrench[:12]) is None  # fewer loads than the form's 13 unknowns


def test_older_calibration_files_model_error_reads_as_it_did():
    """A file from before the load-dependent form (one coefficient per axis against |w / range|)
    and one older still (the validation RMS alone) load, and give the variance they gave."""
    rest = {a: 0.01 * (k + 1) for k, a in enumerate(AXES)}
    per_load = {a: 0.1 * (k + 1) for k, a in enumerate(AXES)}
    older = ModelError.from_report(
        {"validation_error": {"rest": rest, "per_load": per_load, "mean_load": 0.4}}
    )
    assert older.source == "validation"
    w = np.array([5.0, -3.0, 2.0, 0.05, 0.0, -0.02])
    L2 = np.sum((w / SENSOR_RANGE) ** 2)
    expected = np.array(list(rest.values())) ** 2 + np.array(list(per_load.values())) ** 2 * L2
    assert older.variance(w, np.zeros(6), tared=False) == pytest.approx(expected, rel=1e-12)
    oldest = ModelError.from_report({"validation_rmse": rest})
    assert oldest.source == "validation_rmse"
    assert oldest.variance(w, np.zeros(6), tared=True) == pytest.approx(np.array(list(rest.values())) ** 2)


def test_the_model_error_beyond_the_range_is_the_check_poses_and_zero_within():
    """Loads within the range with a small gain error, loads 10-20 times beyond it on Fx with a
    large one: the gain comes from the loads within alone, and the excess beyond from the rest."""
    rng = np.random.default_rng(3813)
    within = np.array([2.0, 2.0, 2.0, 0.2, 0.2, 0.2])
    inside = rng.uniform(-1, 1, (3000, 6)) * within
    outside = rng.uniform(-1, 1, (600, 6)) * within  # beyond the range on Fx alone
    outside[:, 0] = rng.uniform(10, 20, 600) * within[0] * rng.choice([-1, 1], 600)
    wrench = np.vstack([inside, outside])
    spread = np.sqrt(1e-6 + (0.01 * wrench[:, 0]) ** 2)[:, None] * np.ones(6)
    big = np.maximum(np.abs(outside[:, 0]) - within[0], 0.0) * 0.05
    spread[3000:] = np.sqrt(spread[3000:] ** 2 + big[:, None] ** 2)
    error = rng.standard_normal(spread.shape) * spread
    fitted = error_model(error, wrench, 0.0, "poses", within)
    assert fitted is not None and fitted["loads"] == 3000 and fitted["loads_beyond"] == 600
    m = ModelError.from_report({"error_model": fitted})
    # 15 %: as above; fitted on every load together, the range's terms would take several
    # times the error they show within it.
    edge = np.array([2.0, 0, 0, 0, 0, 0])
    assert np.sqrt(m.variance(edge, np.zeros(6), False)[0]) == pytest.approx(math.hypot(1e-3, 0.02), rel=0.15)
    assert m.beyond[0, 0] == pytest.approx(0.05, rel=0.15)
    assert m.variance(edge, np.zeros(6), False)[0] == pytest.approx(
        m.variance(edge * (1 - 1e-12), np.zeros(6), False)[0], rel=1e-9
    )  # continuous at the range's edge: the last term starts from zero there


def test_the_subscriber_gives_each_wrench_its_sigma_and_old_subscriptions_never_see_it(zmq_context):
    endpoint = f"inproc://sigma{uuid.uuid4().hex}"
    pub = zmq_context.socket(zmq.PUB)
    pub.bind(endpoint)
    sigma = np.array([0.02, 0.03, 0.02, 0.003, 0.003, 0.003])
    try:
        with (
            Subscriber(endpoint, ["wrench/sensor1"], context=zmq_context) as new,
            Subscriber(endpoint, ["wrench/sensor1"], latest=True, context=zmq_context) as latest,
        ):
            old = zmq_context.socket(zmq.SUB)  # an old client: the wrench's topic and its NUL
            old.setsockopt(zmq.SUBSCRIBE, b"wrench/sensor1\0")
            old.connect(endpoint)
            try:
                time.sleep(0.2)  # inproc subscriptions reach the publisher asynchronously
                for seq in range(3):
                    pub.send(wire.encode("sigma/wrench/sensor1", wire.KIND_SIGMA, seq, 1.0, 2.0, 0, sigma))
                    pub.send(wire.encode("wrench/sensor1", wire.KIND_WRENCH, seq, 1.0, 2.0, 0, np.zeros(6)))
                pub.send(wire.encode("wrench/sensor1", wire.KIND_WRENCH, 3, 1.0, 2.0, 0, np.zeros(6)))
                got = [new.receive(timeout_s=2) for _ in range(4)]
                assert [s.kind for s in got if s] == [wire.KIND_WRENCH] * 4
                assert all(np.array_equal(s.sigma, sigma) for s in got[:3] if s)
                assert got[3] is not None and got[3].sigma is None  # no companion of seq 3
                last = latest.receive(timeout_s=2)
                assert last is not None and last.seq == 3
                olds = []
                while old.poll(500):
                    olds.append(wire.decode(old.recv()))
                assert [s.topic for s in olds] == ["wrench/sensor1"] * 4
            finally:
                old.close(linger=0)
    finally:
        pub.close(linger=0)


@pytest.mark.parametrize("load", [np.zeros(6), np.array([6.0, -4.0, 8.0, 0.05, -0.04, 0.03])])
def test_the_nonlinear_sigma_is_a_monte_carlo_of_the_chips_noise_through_its_solve(load):
    """The packaged calibration's flux model at a load (none, and one off the rest pose), the
    chips' noise drawn 400 times and each draw solved: the wrench's spread per axis against
    the noise part of the sigma, with every chip and with one left out; and against the map
    without the background field's columns, which the solve estimates (half the spread)."""
    cal = Calibration.load(builtin_path("sim-sensor1.json"))
    assert cal.nonlinear is not None and cal.model.H is not None
    nl = cal.nonlinear
    estimator = nl.estimator()
    sigma_t = channel_sigma_t(mlx.Settings(), 8)
    u = Uncertainty(cal.model, sigma_t, cal.report, estimator)
    T = se3.exp_se3(nl.zero_twist + np.linalg.solve(nl.K, load))
    b = estimator.model.predict(T)
    rng = np.random.default_rng(3814)
    noise = rng.standard_normal((400, 24)) * sigma_t
    for out in (None, 3):
        chips = EVERY.copy()
        if out is not None:
            chips[out] = False
        spread = np.std([nl.wrench(estimator.estimate(b + n, chips, start=T).xi) for n in noise], axis=0)
        maps = u.maps(0, "nonlinear", chips, None, (T, np.zeros(3)))
        assert maps is not None
        predicted = np.sqrt(maps[1])
        # 12 %: a spread from 400 draws is within 3.5 % (1 / sqrt(2 n)) at 1 sigma; the solve is
        # linear in the noise to a few % of it at these loads.
        assert spread == pytest.approx(predicted, rel=0.12), f"chip {out} out"
        if out is None:
            full = predicted
        else:
            assert np.all(predicted > full)  # a chip left out widens every axis's
    without_field = np.sqrt(np.diag(propagate(nl.K @ np.linalg.pinv(cal.model.H), sigma_t)))
    assert np.all(full[2:] > 1.4 * without_field[2:])  # Fz and the torques: the field's share


def test_calibrate_records_the_linear_maps_error_over_the_range_and_it_holds_off_the_plan(small_dataset):
    """`calibrate`'s linear error model comes from the flux model over the range, the nonlinear
    one from the poses; off the plan's arms (a pure force, a pure torque) the linear map's error
    on the loaded axis, on the scene itself, lies within 3 of the sigma's model part."""
    cal, result = calibrate(small_dataset, allow_poor_fit=True)
    assert cal.report["error_model"]["source"] == "flux model"
    assert cal.report["nonlinear"]["error_model"]["source"] == "poses"
    m = ModelError.from_report(cal.report)
    scene = two_sensor_scene()
    addresses = scene.sensors[0].addresses

    def flux(w: np.ndarray) -> np.ndarray:
        scene.set_load(0, StaticLoad(w))
        return np.concatenate([scene.field_t(a, 0.0) for a in addresses])

    tared = cal.model.with_zero(flux(np.zeros(6)))
    assert np.all(m.variance(np.zeros(6), np.zeros(6), tared=True) == 0)
    for k in range(6):
        w = np.zeros(6)
        w[k] = 0.9 * cal.wrench_range[k]
        read = tared.wrench(flux(w))
        sigma = np.sqrt(m.variance(read, np.zeros(6), tared=True))
        assert sigma[k] > 0
        # 3 sigma: a bias of the map at one load, judged against its spread over the range's
        # loads (a Gaussian's 99.7 %); the noise part left out, the scene read without it. The
        # loaded axis's own error (its gain's): the cross-talk onto the other axes at a load of
        # one axis alone can exceed it (docs/design/estimators.md, "Each sample's sigma").
        assert abs(read[k] - w[k]) <= 3 * sigma[k], AXES[k]


def test_the_model_error_is_asked_at_the_load_less_the_readings_noise():
    """A reading within its noise of no load adds no model error (the noise is not a load); one
    beyond it, the model error of its size less that margin."""
    m = ModelError(np.zeros(6), np.full((6, 6), 1e-3), np.full((6, 6), 0.05), np.zeros((6, 6)), 0.0, "poses")
    known = np.full(6, 0.02)
    assert np.all(m.variance(np.full(6, 0.019), np.zeros(6), True, known) == 0)
    w = np.array([1.0, 0, 0, 0, 0, 0])
    shrunk = m.variance(w, np.zeros(6), True, known)
    assert shrunk == pytest.approx(m.variance(w - 0.02 * np.sign(w), np.zeros(6), True), rel=1e-12)
    assert np.all(shrunk < m.variance(w, np.zeros(6), True))


def test_a_calibration_file_with_its_validation_rms_alone_gives_it_as_the_model_error(tmp_path):
    """The oldest files: the report's validation RMS only, the same error at any load."""
    doc = json.loads(builtin_path("sim-sensor1.json").read_text())
    for held in ("error_model", "validation_error"):
        doc["fit_report"].pop(held, None)
    doc["checksum"] = checksum(doc)
    (tmp_path / "cal.json").write_text(json.dumps(doc))
    m = ModelError.from_report(Calibration.load(tmp_path / "cal.json").report)
    rmse = np.array([doc["fit_report"]["validation_rmse"][a] for a in AXES])
    assert m.source == "validation_rmse"
    for w in (np.zeros(6), np.array([2.0, 0, 0, 0, 0.1, 0])):
        assert m.variance(w, np.zeros(6), tared=False) == pytest.approx(rmse**2, rel=1e-12)


@pytest.mark.parametrize("form", ["validation_error", "error_model"])
def test_a_calibration_file_with_either_model_error_form_loads_and_gives_its_sigma(tmp_path, form):
    """The packaged file, its model error removed, with the form of the files written before
    `error_model` (`validation_error`) or with `error_model` in its report, checksum made
    again: it loads, and the sigma reads the form it holds."""
    doc = json.loads(builtin_path("sim-sensor1.json").read_text())
    for held in ("error_model", "validation_error"):  # the packaged file's own, replaced below
        doc["fit_report"].pop(held, None)
    rest = {a: 0.01 for a in AXES}
    if form == "validation_error":
        doc["fit_report"][form] = {
            "rest": rest,
            "per_load": {a: 0.05 for a in AXES},
            "mean_load": 0.4,
            "poses": 60,
        }
    else:
        doc["fit_report"][form] = {
            "rest": rest,
            "spread": {a: [0.0] * 6 for a in AXES},
            "gain": {a: [0.02] * 6 for a in AXES},
            "curvature": {a: [0.0] * 6 for a in AXES},
            "beyond": {a: [0.0] * 6 for a in AXES},
            "within": None,
            "mean_load": 0.4,
            "loads": 4000,
            "loads_beyond": 0,
            "source": "flux model",
        }
    doc["checksum"] = checksum(doc)
    path = tmp_path / "cal.json"
    path.write_text(json.dumps(doc))
    cal = Calibration.load(path)
    m = ModelError.from_report(cal.report)
    assert m.source == ("validation" if form == "validation_error" else "flux model")
    w = np.array([2.0, 0, 0, 0, 0, 0])
    expected = (
        0.01**2 + (0.05 * 2.0 / SENSOR_RANGE[0]) ** 2
        if form == "validation_error"
        else 0.01**2 + (0.02 * 2.0) ** 2
    )
    assert m.variance(w, np.zeros(6), tared=False)[0] == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize(
    ("noise", "lsb"), [(0.0, 6.0), (0.224, 6.009), (2.0, 6.009), (3.0, 9.68), (6.0, 6.0)]
)
def test_the_undithered_quantisation_is_a_monte_carlo_of_the_mean_reading_at_a_held_field(noise, lsb):
    """The RMS over fields of the mean of many rounded noisy readings against the field: the
    part of LSB^2 / 12 the noise does not dither (all of it without noise, none at a noise of
    an LSB), as the chips' conversion rounds (`sim.conversion`)."""
    rng = np.random.default_rng(3)
    field = rng.uniform(0.0, lsb, 1500)
    readings = np.round((field[:, None] + rng.normal(0.0, noise, (1500, 4000))) / lsb) * lsb
    bias = readings.mean(axis=1) - field
    # The mean's own noise, sigma / sqrt(4000) a field, taken off the mean square.
    measured = math.sqrt(max(float(np.mean(bias**2)) - (noise**2 + lsb**2 / 12) / 4000, 0.0))
    expected = float(undithered(np.array([noise]), np.array([lsb]))[0])
    if noise == 0.0:
        assert expected == pytest.approx(lsb / math.sqrt(12), rel=1e-4)
    # 5 % of LSB / sqrt(12) or of the value: 1500 fields' spread of a sawtooth's square.
    assert measured == pytest.approx(expected, rel=0.05, abs=0.01 * lsb)


def test_the_undithered_quantisation_is_none_at_the_tares_load_and_twice_its_share_under_one(quiet_rig):
    """After a tare, at its load the quantisation's bias is the tare's own (none in the sigma);
    once a load has moved every channel's field by more than an LSB, 2 q^2 a channel through
    the map; the filter shrinks only the rest of the noise."""
    p = quiet_rig.daemon.sensors[0]
    u = p.uncertainty
    quiet_rig.cycles(2)
    p.tare(p.model.zero, None, 100)
    noise, diag, offset = u.maps(p.version, "linear", EVERY, 100)
    q = (p.model.KA**2) @ u.bias_t**2
    assert np.allclose(diag, (p.model.KA**2) @ (u.sigma_t**2 - u.bias_t**2))
    at_rest = u.sample(p.version, "linear", EVERY, np.zeros(6), p.tare_wrench, True, 100, 0.01)
    load = np.array([2.0, -2.0, 2.0, 0.15, -0.15, 0.15])  # the range's edge: every field moved
    held = u.sample(p.version, "linear", EVERY, load, p.tare_wrench, True, 100, 0.01)
    known = NOISE_SIGMAS * np.sqrt(0.01 * diag + diag / 100)
    model = u.linear_error.variance(load, p.tare_wrench, True, known)
    # Each channel's field moved by d LSBs: 2 q^2 min(1, 2 pi^2 d^2), through K A.
    moved = np.abs(np.linalg.pinv(p.model.KA) @ (np.sign(load) * (np.abs(load) - known))) / u.lsb_t
    share = np.minimum(1.0, 2 * np.pi**2 * moved**2)
    assert held.model - model == pytest.approx(2 * (p.model.KA**2) @ (u.bias_t**2 * share), rel=1e-9)
    # Most fields moved past the small-d form: about 2 q^2 (a channel or so this load barely moves).
    assert np.mean(share == 1.0) > 0.9 and held.model - model == pytest.approx(2 * q, rel=0.15)
    assert at_rest.model == pytest.approx(
        u.linear_error.variance(np.zeros(6), p.tare_wrench, True, np.zeros(6)), rel=1e-12
    )
    # status's prediction at rest leaves it out; the accuracy plan's (under a load) holds it.
    rest = np.array(u.predicted(0.01, 100)["sigma"]) ** 2
    loaded = np.array(u.predicted(0.01, 100, loaded=True)["sigma"]) ** 2
    assert loaded - rest == pytest.approx(2 * q, rel=1e-3)  # (its sigma rounded to 1e-7)


@pytest.mark.parametrize("solver", ["numpy", "compiled"])
def test_the_nonlinear_sigma_takes_the_jacobian_the_solve_keeps(monkeypatch, tmp_path, solver):
    """The daemon's pipeline on a held load and on one that changes every sample: the sigma
    makes no Jacobian of the flux model of its own (`NonlinearEstimator.jacobian_at` hands it
    the one the solve keeps), so steps with it make as many as steps without; and its noise
    map is the solve's gains at that Jacobian, of the noise the filter shrinks, with the
    undithered quantisation's maps through the same gains, made again with them when the solve
    keeps a new Jacobian."""
    from ftsensord.acquire.readings import Readings
    from ftsensord.config.file import load_config
    from ftsensord.model import nlcompiled
    from ftsensord.processing.pipeline import SensorPipeline
    from ftsensord.sim.scene import default_scene

    from .test_nonlinear import count_calls

    library = None
    if solver == "compiled":  # built here, as a fresh clone's tests find it (CI: a C compiler)
        if nlcompiled.compiler() is None:
            if os.environ.get("CI"):
                pytest.fail("no C compiler (cc or gcc) on PATH: CI must build and test the compiled solver")
            pytest.skip("no C compiler (cc or gcc) on PATH")
        library = nlcompiled.compile_library(tmp_path)
    scene, rng = default_scene(), np.random.default_rng(7)
    sensor = scene.sensors[0]
    readings = []
    for i in range(40):
        moving = i >= 20  # 20 samples of one held load, then a new load every sample
        w = np.r_[rng.uniform(-1, 1, 3), rng.uniform(-0.02, 0.02, 3)] if moving else np.r_[1.0, 0, 0, 0, 0, 0]
        scene.set_load(sensor.name, StaticLoad(w))
        flux = np.concatenate([scene.field_t(a, 100.0) for a in sensor.addresses])
        readings.append(Readings.of_field(sensor.addresses, flux + rng.normal(0, 1e-7, flux.size)))
    counts, kept = [], []
    for with_sigma in (False, True):
        p = SensorPipeline.build(load_config().sensors[0], WrenchFilter(), 2, thermal=False, rate_hz=100.0)
        p.use("nonlinear")
        assert p.nonlinear is not None and p.uncertainty is not None
        nlcompiled.attach(p.nonlinear, solver, library)
        if not with_sigma:
            p.uncertainty = None
        counted = count_calls(monkeypatch, p.nonlinear.model, "predict_and_jacobian")
        for i, r in enumerate(readings):
            sample = p.step(r)
            assert np.all(np.isfinite(sample.sigma.sigma)) == with_sigma
            if with_sigma and i in (10, 19):  # the held load's maps: its variances per axis
                kept.append(p.uncertainty.maps(p.version, "nonlinear", EVERY, None)[1])  # type: ignore[index]
            if with_sigma and i == 19:  # the held load's quantisation maps (untared: q^2 a channel)
                key = (p.version, "nonlinear", EVERY.tobytes())
                held = p.uncertainty.quantisation(key, np.zeros(6), np.zeros(6), False).copy()
        counts.append(counted["calls"])
    # numpy's solve makes its Jacobians in Python, the compiled one in C: none from the sigma
    assert counts[1] == counts[0] and (counts[0] > 0) == (solver == "numpy")
    assert kept[0] is kept[1]  # the held load's solve kept its Jacobian: its maps were not made again
    nl = p.nonlinear
    version, J = nl.jacobian_at(nl.pose, nl.background_t)
    # Its version is the kept Jacobian's: the same again (no copy for who has it), a new one
    # with a new Jacobian (past the reuse rule's 40 um).
    assert nl.jacobian_at(nl.pose, nl.background_t, version) == (version, None)
    moved = nl.pose.copy()
    moved[0, 3] += 2 * JACOBIAN_REUSE_M
    other, J_moved = nl.jacobian_at(moved, nl.background_t, version)
    assert other != version and J_moved is not None and not np.allclose(J_moved, J, rtol=1e-6, atol=0)
    assert nl.jacobian_at(nl.pose, nl.background_t, other)[0] not in (version, other)  # and back: another
    # A new compiled solve counts its Jacobians from one again: its first is not another
    # solve's first.
    nlcompiled.attach(nl, solver, library)
    assert nl.jacobian_at(nl.pose, nl.background_t, (object(), 1))[1] is not None
    version, J = nl.jacobian_at(nl.pose, nl.background_t)
    maps = p.uncertainty.maps(p.version, "nonlinear", EVERY, None, (nl.pose, nl.background_t))
    assert maps is not None
    M = nl.stiffness @ np.linalg.solve(J.T @ J + np.diag([0.0] * 6 + [PRIOR_WEIGHT] * 3), J.T)[:6]
    u = p.uncertainty
    assert maps[0] == pytest.approx(propagate(M, u.independent_t), rel=1e-9)
    q = u.quantisation((p.version, "nonlinear", EVERY.tobytes()), np.zeros(6), np.zeros(6), False)
    assert np.all(q > 0) and q == pytest.approx((M * M) @ u.bias_t**2, rel=1e-9)
    assert not np.allclose(q, held, rtol=1e-6, atol=0)  # made again with the new Jacobian


def test_at_the_longest_conversion_the_sigma_at_the_tares_field_is_the_tares_own_spread(tmp_path):
    """At OSR 3, DIG_FILT 7 the chips' noise is a small part of an LSB: at a held field only
    the channels near a step of it toggle, so the noise over the fields (what a load brings)
    is far off the one at the tare's field. After a tare through the control request, status
    and each sample's sigma take its samples' spread, and the spread that follows is it."""
    r = Rig(tmp_path, "temperature_every = 0", chip="osr = 3\ndig_filt = 7", rate_hz=3)
    try:
        r.cycles(20)
        r.req.send(json.dumps({"cmd": "tare", "samples": 200}).encode())
        r.daemon.handle_control()
        r.cycles(200)
        assert json.loads(r.req.recv())["ok"]
        p = r.daemon.sensors[0]
        u = p.uncertainty
        assert p.tare_samples == 200 and p.tare_spread is not None
        out = r.cycles(800)
        wrench = np.array([s.values for s in out["wrench/sensor1"]])
        sigma = np.array([s.values for s in out["sigma/wrench/sensor1"]])
        status = np.array(r.request(cmd="status")["result"]["sensors"]["sensor1"]["sigma"]["sigma"])
        at_rest = u.predicted(1.0, 200, spread=p.tare_spread)["sigma"]
        over_fields = np.sqrt(u.maps(p.version, "linear", EVERY, 200)[1] * (1 + 1 / 200))
        # A load that moves every field many chip noise sigmas: the noise over the fields
        # again (the tare's offset stays its own samples'); the covariance says the same.
        load = np.array([2.0, -2.0, 2.0, 0.15, -0.15, 0.15])
        args = (p.version, "linear", EVERY)
        loaded = u.sample(*args, load, p.tare_wrench, True, 200, 1.0, spread=p.tare_spread)
        rest = u.sample(*args, np.zeros(6), p.tare_wrench, True, 200, 1.0, spread=p.tare_spread)
        _, diag, offset = u.maps(*args, 200)
    finally:
        r.close()
    # The samples' spread about their mean and the tare's offset against that mean: what the
    # sigma holds, as the model error is left out (at the tare's load: none of its rest term).
    measured = np.sqrt(wrench.var(axis=0) + (wrench.mean(axis=0)) ** 2)
    model = u.linear_error.variance(np.zeros(6), p.tare_wrench, True)
    noise = np.sqrt(np.maximum(np.array(at_rest) ** 2 - model, 0.0))
    assert status == pytest.approx(at_rest, rel=1e-6)  # status shows the same
    # as do the samples at rest (1e-4: the 7 decimals status rounds to, at 1e-3 Nm)
    assert np.median(sigma, axis=0) == pytest.approx(at_rest, rel=1e-4)
    # 30 %: a toggling channel's rate from 200 and 800 samples (a few tens of toggles each).
    assert measured == pytest.approx(noise, rel=0.3)
    # ...where the noise over the fields misses it by far on some axis (this part's).
    assert np.max(np.abs(np.log(measured / over_fields))) > np.log(2.0)
    # 10 %: a channel or so this load barely moves keeps part of its tare's weight.
    assert loaded.sigma**2 - loaded.model == pytest.approx(diag + offset.diagonal(), rel=0.1)
    assert rest.sigma == pytest.approx(np.array(at_rest), rel=1e-4)  # status rounds to 7 decimals
    for s in (loaded, rest):  # 1e-12: round-off
        assert np.diag(s.covariance()) == pytest.approx(s.sigma**2, rel=1e-12)


def test_a_short_tares_spread_is_not_taken_and_another_conversion_drops_it(quiet_rig):
    """Under `SPREAD_SAMPLES` a tare's spread says too little of each channel: the noise over
    the fields stays. A reload that keeps the calibration keeps the tare, and its spread only
    while the chips' settings (their noise) are the same."""
    p = quiet_rig.daemon.sensors[0]
    u = p.uncertainty
    flux = []
    for _ in range(SPREAD_SAMPLES + 2):
        quiet_rig.cycles(1)
        flux.append(p.last_flux.copy())
    tare_on(p, flux[: SPREAD_SAMPLES - 1])
    few = u.maps(p.version, "linear", EVERY, p.tare_samples, spread=p.tare_spread)
    assert p.tare_spread is not None and few is not None
    assert few[1] == pytest.approx((p.model.KA**2) @ u.independent_t**2, rel=1e-12)
    tare_on(p, flux)
    enough = u.maps(p.version, "linear", EVERY, p.tare_samples, spread=p.tare_spread)
    assert enough is not None and np.allclose(
        enough[2], (p.model.KA * p.tare_spread) @ p.model.KA.T / len(flux)
    )
    same = replace(p, tare_spread=None)
    carry_tares([p], [same])
    assert same.tare_spread is not None and np.array_equal(same.tare_spread, p.tare_spread)
    other = replace(p, tare_spread=None, sigma_t=2 * p.sigma_t)
    carry_tares([p], [other])
    assert other.tared and other.tare_spread is None
