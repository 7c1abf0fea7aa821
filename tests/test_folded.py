"""The usual sample's one product (`FoldedCheck`, `RedundancyCheck.usual`) gives what the
separate steps give: the temperature stage, the redundancy check's three tests, the linear
wrench and its extrapolation flag, sample by sample, and hands every other sample to them
untouched."""

from __future__ import annotations

import numpy as np
import pytest

from ftsensord.acquire.readings import Readings
from ftsensord.chip import mlx90393 as mlx
from ftsensord.config.file import builtin_path, load_config
from ftsensord.model.consistency import FoldedCheck
from ftsensord.model.linear import EXTRAPOLATION_MARGIN, SENSOR_RANGE, LinearModel
from ftsensord.processing.filters import WrenchFilter
from ftsensord.processing.pipeline import SensorPipeline, channel_sigma_t
from ftsensord.protocol import wire
from ftsensord.sim.loads import StaticLoad
from ftsensord.sim.scene import default_scene

from .test_consistency import packaged_model

SIGMA_T = channel_sigma_t(mlx.Settings(), 8)


@pytest.mark.parametrize("room", [False, True, "gradient"])
def test_the_folded_sums_are_the_checks(room):
    """chi2, the drops (squares here, products there), the gradient's size, the model's wrench
    and both loads equal the separate computations, with the temperature stage's scale and
    shift folded in, for noise-sized and 30x residuals and one channel far off."""
    model = packaged_model(room)
    rng = np.random.default_rng(5)
    every = np.ones(8, dtype=bool)
    scale, shift = 1 + rng.normal(0, 2e-3, 24), rng.normal(0, 3e-6, 24)
    tare, fitted = rng.normal(0, 1, 6), np.array([40.0, 40.0, 60.0, 0.5, 0.5, 0.4])
    f = model.folded(SIGMA_T, scale, shift, tare, 1 / fitted, 1 / (EXTRAPOLATION_MARGIN * fitted))
    assert isinstance(f, FoldedCheck)
    k = f.gradient_dof
    for trial in range(40):
        b = model.zero + SIGMA_T * rng.normal(0, 1, 24) * rng.choice([1.0, 30.0])
        b[rng.integers(24)] += 40e-6 * (trial % 2)
        y, sums = f.apply(b)
        reference = b * scale - shift
        c = model.consistency(reference, SIGMA_T, every)
        # Round-off: whitened sums of a few to thousands of sigma^2, and c's cancellation
        # (the flux over its noise, 1e4, times 1e-16).
        assert sums[0] == pytest.approx(c.chi2, rel=1e-9, abs=1e-9)
        np.testing.assert_allclose(sums[1:9], c.drop, rtol=1e-9, atol=1e-9 * (1 + c.chi2))
        assert sums[9] == pytest.approx(c.gradient_chi2, rel=1e-9, abs=1e-9)
        assert (sums[9] == 0.0) is (k == 0)
        w = model.wrench(reference)
        np.testing.assert_allclose(y[f.wrench], w, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(sums[10:16], ((c.wrench + tare) / fitted) ** 2, rtol=1e-9, atol=1e-15)
        np.testing.assert_allclose(
            sums[16:22], ((w + tare) / (EXTRAPOLATION_MARGIN * fitted)) ** 2, rtol=1e-9, atol=1e-15
        )


def test_chips_that_cannot_leave_drop_nothing():
    """The singular end: three chips, 9 channels, 6 unknowns: no chip can be left out (the
    rest would see fewer channels than unknowns), so no Cholesky is taken and every drop
    is 0, as the separate check's."""
    rng = np.random.default_rng(2)
    H, K = rng.normal(0, 1, (9, 6)), np.eye(6)
    model = LinearModel(K, np.linalg.pinv(H), np.zeros(9), H)
    sigma = np.full(9, 1e-6)
    maps = model._maps(np.ones(3, dtype=bool), sigma)
    assert maps.stays.all() and not maps.chip_rows.any()
    f = model.folded(sigma, None, None, np.zeros(6), np.ones(6), np.zeros(6))
    assert f is not None
    b = rng.normal(0, 1e-5, 9)
    y, sums = f.apply(b)
    assert sums[1:4] == [0.0, 0.0, 0.0]
    assert sums[0] == pytest.approx(model.consistency(b, sigma, np.ones(3, dtype=bool)).chi2, rel=1e-9)
    assert max(sums[-6:]) == 0.0  # no bound: nothing extrapolated


def test_no_fold_without_redundancy():
    """Two chips, 6 channels for 6 unknowns: nothing to check, no fold (the separate way decides)."""
    rng = np.random.default_rng(3)
    H = rng.normal(0, 1, (6, 6))
    model = LinearModel(np.eye(6), np.linalg.inv(H), np.zeros(6), H)
    assert model.folded(np.full(6, 1e-6), None, None, np.zeros(6), np.ones(6), np.zeros(6)) is None
    no_h = LinearModel(np.eye(6), np.linalg.inv(H), np.zeros(6))
    assert no_h.folded(np.full(6, 1e-6), None, None, np.zeros(6), np.ones(6), np.zeros(6)) is None


def _pair():
    """Two pipelines of the packaged sensor 1, the second never taking the one product."""
    config = load_config(builtin_path("sim.toml"))
    s = config.sensors[0]
    usual, separate = (
        SensorPipeline.build(s, WrenchFilter(), config.max_missing_chips, config.settings) for _ in range(2)
    )
    separate.check.usual = lambda *args: None  # type: ignore[method-assign]
    return s, usual, separate


def test_the_usual_sample_is_the_separate_ones():
    """Sample by sample, through a temperature change, a tare, loads up to 1.8x the
    calibration's (extrapolated past 1.5x), a chip off by 8 sigma (found out, kept out until
    it agrees again) and one drifting a third of a sigma a sample (the slow test's): the
    one-product pipeline gives the separate pipeline's wrench, flags and check state."""
    s, usual, separate = _pair()
    cal = s.calibration
    scene, rng = default_scene(), np.random.default_rng(8)
    sigma = SIGMA_T
    answers = []
    inner = usual.check.usual
    usual.check.usual = lambda *args: answers.append(inner(*args)) or answers[-1]  # type: ignore[method-assign]
    extrapolated = 0
    for k in range(400):
        if k == 50:
            for p in (usual, separate):
                p.thermal.observe([30.0 + 0.3 * i for i in range(8)])
        if k == 100:
            zero = np.concatenate([scene.field_t(a, 0.0) for a in s.addresses])
            for p in (usual, separate):
                p.tare(zero)
        u = np.sin(np.arange(6) + k / 17)
        scene.set_load(0, StaticLoad(u * cal.wrench_range * (1.8 if 200 <= k < 230 else 0.3)))
        b = np.concatenate([scene.field_t(a, 0.0) for a in s.addresses]) + sigma * rng.normal(0, 1, 24)
        if 260 <= k < 270:
            b[9:12] += 8 * sigma[9:12]  # chip 3 off by 8 sigma for ten samples
        if 300 <= k < 360:
            b[15:18] += (k - 300) * 0.35 * sigma[15:18]  # chip 5 drifting
        got = usual.step(Readings.of_field(s.addresses, b))
        want = separate.step(Readings.of_field(s.addresses, b))
        extrapolated += bool(got.flags & wire.FLAG_EXTRAPOLATED)
        assert got.flags == want.flags, k
        # Round-off: the folded constant's cancellation, 1e-12 of the wrench's scale.
        np.testing.assert_allclose(got.wrench, want.wrench, rtol=1e-9, atol=1e-12, err_msg=str(k))
        assert usual.check.inconsistent == separate.check.inconsistent
        assert usual.check.suspects == separate.check.suspects
        assert usual.check.slow_count == separate.check.slow_count
    assert usual.check.inconsistent >= 2, "neither the chip off nor the drifting one was found"
    assert extrapolated >= 10, "the loads beyond 1.5x were not flagged extrapolated"
    taken = sum(a is not None for a in answers)
    assert taken > 250, f"the one product took only {taken} of 400 samples"
    assert any(a is not None and a[1] for a in answers), "no extrapolated sample went the one product's way"


def test_overload_is_flagged_axis_by_axis():
    """The overload flag, whichever way the sample went: set exactly when the estimate is
    beyond SENSOR_RANGE on some axis (the default filter passes the wrench through), loads
    from a tenth of the range to 1.6 times it on each axis."""
    s, usual, _ = _pair()
    scene, seen = default_scene(), set()
    for axis in range(6):
        for size in (0.1, 0.3, 0.6, 1.0, 1.6):
            u = np.zeros(6)
            u[axis] = size * SENSOR_RANGE[axis]
            scene.set_load(0, StaticLoad(u))
            b = np.concatenate([scene.field_t(a, 0.0) for a in s.addresses])
            got = usual.step(Readings.of_field(s.addresses, b))
            over = bool(np.any(np.abs(got.wrench) > SENSOR_RANGE))
            assert bool(got.flags & wire.FLAG_OVERLOAD) is over, (axis, size, got.wrench)
            seen.add(over)
    assert seen == {False, True}
