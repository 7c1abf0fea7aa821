"""The redundancy check, filters that carry flags, and the tare's rules: every wrong
wrench is flagged, and a tare takes nothing that is."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ftsensord.calibration.calfile import Calibration
from ftsensord.chip import mlx90393 as mlx
from ftsensord.config.file import builtin_path
from ftsensord.model.consistency import Consistency, chi2_quantile
from ftsensord.processing.filters import WrenchFilter
from ftsensord.processing.pipeline import channel_sigma_t
from ftsensord.processing.redundancy import (
    CHIP_RESIDUAL_AT_RANGE,
    CHIP_RESIDUAL_AT_REST,
    MODEL_RESIDUAL_AT_RANGE,
    MODEL_RESIDUAL_AT_REST,
    SLOW_WINDOW,
    RedundancyCheck,
    _slow_limit,
    every_chip,
)
from ftsensord.protocol import wire
from ftsensord.sim.loads import StaticLoad
from ftsensord.sim.scene import default_scene

from .test_daemon import LOAD, Rig, write_config
from .test_faults import fault

SETTINGS = mlx.Settings()
SIGMA_T = channel_sigma_t(SETTINGS, 8)
#: The moving load of the fault tests (N, Nm; periods s): about a twelfth of the calibration's
#: largest load, where K A's own error stays within 1 sigma on the default scene's as-built
#: sensor in the room (twice as much reached 1.9 sigma: with the noise, 5.1 sigma fault-free
#: in 3000 draws; benchmarks/accuracy/faults_truth.py).
AMPLITUDE = np.array([0.175, 0.15, 0.15, 0.01, 0.014, 0.01])
PERIOD_S = np.array([4.0, 5.3, 3.1, 4.7, 6.1, 3.7])


class Moving:
    def wrench(self, t: float) -> np.ndarray:
        return AMPLITUDE * np.sin(2 * np.pi * t / PERIOD_S + np.arange(6))


def test_chi2_quantile_matches_the_distribution():
    rng = np.random.default_rng(0)
    for dof in (1, 3, 12, 15, 18):
        draws = (rng.standard_normal((200_000, dof)) ** 2).sum(axis=1)
        for odds in (0.1, 0.01):
            # 200,000 draws: the fraction's standard error is under 0.07 of 0.01.
            assert np.mean(draws > chi2_quantile(dof, odds)) == pytest.approx(odds, rel=0.1)
    with pytest.raises(ValueError):
        chi2_quantile(0, 0.1)


@pytest.mark.parametrize("name, index", [("sim-sensor1.json", 0), ("sim-sensor2.json", 1)])
def test_the_model_error_bounds_cover_the_calibrations_largest_loads(name, index):
    """The linear model's own residual, noise-free, at up to 1.5 times the calibration's
    largest loads, stays below the allowance the threshold adds for it."""
    cal = Calibration.load(builtin_path(name))
    scene, rng = default_scene(), np.random.default_rng(3)
    for k in range(150):
        u = rng.uniform(-1, 1, 6) if k % 2 else rng.choice([-1.0, 0.0, 1.0], 6)
        if not np.any(u):
            continue
        for s in (0.1, 0.5, 1.0, 1.5):
            scene.set_load(index, StaticLoad(u / np.max(np.abs(u)) * s * cal.wrench_range))
            b = np.concatenate([scene.field_t(a, 0.0) for a in cal.addresses])
            c = cal.model.consistency(b, SIGMA_T, np.ones(8, bool))
            assert np.sqrt(c.chi2) < MODEL_RESIDUAL_AT_REST + MODEL_RESIDUAL_AT_RANGE * s**2
            assert (
                np.sqrt(np.max(c.chi2 - c.chi2_without))
                < CHIP_RESIDUAL_AT_REST + CHIP_RESIDUAL_AT_RANGE * s**2
            )


def test_no_false_alarm_at_the_calibrations_largest_loads_with_noise(tmp_path):
    """N = 20,000 noisy, quantised samples at the corners and edges of the calibration's
    loads (every axis at 0 or +-1 times its largest): none flagged inconsistent."""
    rig = Rig(tmp_path)
    p = rig.daemon.sensors[0]
    cal = p.config.calibration
    scene, rng = default_scene(), np.random.default_rng(7)
    lsb = np.tile([SETTINGS.sensitivity_ut(a) * 1e-6 for a in "xyz"], 8)
    noise = np.tile([SETTINGS.noise_ut(a) * 1e-6 for a in "xyz"], 8)
    flagged = 0
    for _ in range(200):
        scene.set_load(0, StaticLoad(rng.choice([-1.0, 0.0, 1.0], 6) * cal.wrench_range))
        b = np.concatenate([scene.field_t(a, 0.0) for a in cal.addresses])
        for _ in range(100):
            # The chip's reading: its noise, then its LSB (a random offset: where the codes fall).
            q = np.round((b + rng.normal(0, noise) + rng.uniform(-0.5, 0.5, 24) * lsb) / lsb) * lsb
            _, flags = p.estimate(q, 0, np.ones(8, bool))
            flagged += bool(flags & wire.FLAG_INCONSISTENT)
    assert flagged == 0
    rig.close()


def test_no_false_alarm_at_rest_through_the_daemon(tmp_path):
    rig = Rig(tmp_path)
    out = rig.cycles(1000)  # N = 1000 cycles, 2000 samples of two sensors (one loaded)
    for topic in ("wrench/sensor1", "wrench/sensor2"):
        assert len(out[topic]) == 1000 and not any(s.flags & wire.FLAG_INCONSISTENT for s in out[topic])
    rig.close()


def moving_rig(tmp_path, scene_extra: str, seconds: float) -> tuple[Rig, list[wire.Sample], np.ndarray]:
    """sensor1 under the moving load with ``scene_extra``'s faults; returns its samples and
    sigma per axis (sensor2's noise at rest over the same run)."""
    rig = Rig(tmp_path, scene_extra=scene_extra)
    load = Moving()
    rig.scene.set_load("sensor1", load)
    out = rig.cycles(int(seconds * 100))
    sigma = np.std([s.values for s in out["wrench/sensor2"]], axis=0)
    return rig, out["wrench/sensor1"], sigma


def unflagged_errors(samples: list[wire.Sample], sigma: np.ndarray) -> np.ndarray:
    """The largest error (in sigmas, over the axes) of every sample without a value flag."""
    load = Moving()
    out = []
    for s in samples:
        if s.flags & ~wire.FLAG_LATE:
            continue
        # The chips convert through the cycle; the sample is stamped after: 4 ms is mid-cycle.
        out.append(np.max(np.abs(s.values - load.wrench(s.t_mono - 0.004)) / sigma))
    return np.array(out)


def test_a_stuck_chip_under_a_moving_load_never_gives_an_unflagged_wrong_wrench(tmp_path):
    rig, w, sigma = moving_rig(tmp_path, fault("stuck", 0.5, 4.5, address=0x0F), 5.0)
    during = [s for s in w if 0.5 <= s.t_mono < 4.5]
    assert sum(bool(s.flags) for s in during) > 0.5 * len(during)  # it is out most of the fault
    assert np.max(unflagged_errors(w, sigma)) < 5
    assert rig.daemon.reader.health[0x0F].stuck_detections >= 2  # reset, found still stuck, reset again
    rig.close()


def test_a_still_stuck_chip_stays_out_after_its_reset(tmp_path):
    rig = Rig(tmp_path, scene_extra=fault("stuck", 0.2, 3.0, address=0x0F), extra="stuck_cycles = 50")
    w = rig.cycles(300)["wrench/sensor1"]
    first = next(i for i, s in enumerate(w) if s.flags & wire.FLAG_CHIP_MISSING)
    # From its detection to the fault's end, no sample trusts it: before, it rejoined for 50 cycles.
    assert all(s.flags & wire.FLAG_CHIP_MISSING for s in w[first:] if s.t_mono < 3.0)
    rig.close()


def test_a_silent_gain_change_is_flagged_from_its_first_sample(tmp_path):
    # CONF1 to GAIN_SEL 7 at 0.3 s: the chip reads a fifth of the field it should.
    rig, w, sigma = moving_rig(
        tmp_path, fault("drift_register", 0.3, address=0x10, register=0, value=0x007C), 1.0
    )
    after = [s for s in w if s.t_mono > 0.31]
    first = next(i for i, s in enumerate(after) if s.flags)
    assert after[first].flags & wire.FLAG_INCONSISTENT and after[first].t_mono < 0.33
    assert np.max(unflagged_errors(w, sigma)) < 5
    assert rig.daemon.reader.health[0x10].register_drifts == 1  # the read-back still resets it
    rig.close()


def test_a_filtered_output_carries_the_flag_of_every_input_in_it():
    f = WrenchFilter(averaging=5, lowpass_hz=5.0, rate_hz=100.0)
    clean, bad = np.zeros(6), np.full(6, 4.0)
    for _ in range(50):
        assert f.update(clean)[1] == 0
    out = [f.update(bad, wire.FLAG_INCONSISTENT)] + [f.update(clean) for _ in range(f.reach + 5)]
    carried = [flags for _, flags in out]
    assert all(flags & wire.FLAG_INCONSISTENT for flags in carried[: f.reach])
    assert not any(carried[f.reach :])
    # Once unflagged, what is left of the 4 N input is below a fifth of the noise (0.005 N).
    assert np.max(np.abs(out[f.reach][0])) < 4.0 * 1e-3
    assert (
        f.update(clean, wire.FLAG_LATE)[1] == wire.FLAG_LATE and f.update(clean)[1] == 0
    )  # late: not carried


def test_the_daemon_carries_a_flag_through_averaging_and_lowpass(tmp_path):
    scene = fault("saturate", 0.3, 0.32, address=0x12, field_mt=70)
    raw = Rig(tmp_path, scene_extra=scene)
    hit = [i for i, s in enumerate(raw.cycles(60)["wrench/sensor1"]) if s.flags & wire.FLAG_SATURATED]
    raw.close()
    rig = Rig(tmp_path, scene_extra=scene, extra="averaging = 4\nlowpass_hz = 10")
    w = rig.cycles(60)["wrench/sensor1"]
    reach = rig.daemon.sensors[0].filter.reach  # 3 + 15 inputs: the window, then 1e-4 of the memory
    carried = [i for i, s in enumerate(w) if s.flags & wire.FLAG_SATURATED]
    assert carried == list(range(hit[0], hit[-1] + reach))  # same seed: the same cycles saturate
    rig.close()


def tare(rig: Rig, **args) -> None:
    rig.req.send(json.dumps({"cmd": "tare", **args}).encode())
    rig.daemon.handle_control()


def test_a_tare_refuses_flagged_samples_and_says_which_flags(tmp_path):
    rig = Rig(tmp_path, scene_extra=fault("nack", 0.0, 5.0, address=0x0E))
    tare(rig, sensor="sensor1", samples=10)
    rig.cycles(102)
    reply = json.loads(rig.req.recv())
    assert not reply["ok"] and "chip_missing in" in reply["error"] and "degraded in" in reply["error"]
    assert "0 of 10" in reply["error"] and not rig.daemon.sensors[0].tared
    rig.close()


def test_a_tare_refuses_a_moving_load(tmp_path):
    rig = Rig(tmp_path)
    rig.scene.set_load("sensor1", Moving())
    tare(rig, sensor="sensor1", samples=50)
    rig.cycles(51)
    reply = json.loads(rig.req.recv())
    assert not reply["ok"] and "moved during the tare" in reply["error"] and not rig.daemon.sensors[0].tared
    rig.close()


def test_one_tare_per_sensor_at_a_time(tmp_path):
    rig = Rig(tmp_path)
    tare(rig, samples=20)
    other = rig.daemon.control.handle(json.dumps({"cmd": "tare", "sensor": "sensor2"}).encode(), [b"x"])
    assert other is not None and not other["ok"] and "under way" in other["error"]
    untare = rig.daemon.control.handle(json.dumps({"cmd": "untare"}).encode(), [b"y"])
    assert untare is not None and not untare["ok"] and "under way" in untare["error"]
    assert len(rig.daemon.tares.jobs) == 1
    rig.cycles(20)
    assert json.loads(rig.req.recv())["ok"]
    rig.close()


def test_a_tare_survives_a_reload_with_the_same_calibration_and_untare_undoes_it(tmp_path):
    rig = Rig(tmp_path)
    tare(rig, samples=10)
    rig.cycles(10)
    offset = json.loads(rig.req.recv())["result"]["tare_wrench"]["sensor1"]
    reply = rig.request(cmd="reload")
    assert reply["ok"] and reply["result"]["tare"]["sensor1"].startswith("kept")
    assert rig.daemon.sensors[0].tared and np.allclose(rig.daemon.sensors[0].tare_wrench, offset, atol=1e-6)
    w = np.mean([s.values for s in rig.cycles(20)["wrench/sensor1"]], axis=0)
    assert np.allclose(w[:3], 0, atol=0.05)
    removed = rig.request(cmd="untare", sensor="sensor1")["result"]["removed_tare_wrench"]
    assert np.allclose(removed["sensor1"], offset, atol=1e-6) and not rig.daemon.sensors[0].tared
    w = np.mean([s.values for s in rig.cycles(20)["wrench/sensor1"]], axis=0)
    assert np.allclose(w[:3], LOAD[:3], atol=0.3)
    rig.close()


def test_a_reload_with_another_calibration_drops_the_tare_and_says_so(tmp_path):
    rig = Rig(tmp_path)
    tare(rig, samples=10)
    rig.cycles(10)
    assert json.loads(rig.req.recv())["ok"]
    cal = Calibration.load(builtin_path("sim-sensor1.json"))
    cal.model = cal.model.with_zero(cal.model.zero + 1e-7)  # another zero: another calibration
    cal.save(tmp_path / "other.json")
    write_config(tmp_path, sensor1_cal=str(tmp_path / "other.json"), scheduler="overlapped")
    reply = rig.request(cmd="reload")
    assert reply["ok"] and "dropped" in reply["result"]["tare"]["sensor1"]
    assert "sensor2" not in reply["result"]["tare"] or reply["result"]["tare"]["sensor2"].startswith("kept")
    assert not rig.daemon.sensors[0].tared
    rig.close()


def _brute_force(model, b, sigma, chips):
    """chi2 and every leave-one-out chi2 by weighted least squares on each subset, directly."""
    H = model.columns

    def chi2(use):
        ch = np.repeat(use, 3)
        A, x = H[ch] / sigma[ch, None], (b - model.zero)[ch] / sigma[ch]
        if ch.sum() <= A.shape[1] or np.linalg.matrix_rank(A) < A.shape[1]:
            return np.inf, np.full(6, np.nan), 0.0
        theta = np.linalg.lstsq(A, x, rcond=None)[0]
        r = x - A @ theta
        if model.gradient is not None:  # the gradient's estimate, whitened by its covariance
            k = model.gradient.shape[1]
            g = theta[-k:]
            gradient_chi2 = float(g @ np.linalg.solve(np.linalg.inv(A.T @ A)[-k:, -k:], g))
        return float(r @ r), model.K @ theta[:6], gradient_chi2 if model.gradient is not None else 0.0

    whole, wrench, gradient = chi2(chips)
    without = np.full(len(chips), np.inf)
    for c in np.flatnonzero(chips):
        rest = chips.copy()
        rest[c] = False
        without[c] = chi2(rest)[0] if np.isfinite(whole) else np.inf
    return whole, wrench, without, gradient


def packaged_model(room: bool | str):
    """Sensor 1's packaged model; ``room``: blind to the room's field, "gradient": and to a gradient."""
    model = Calibration.load(builtin_path("sim-sensor1.json")).model
    if room:
        model = model.rejecting_room_field()
    if room == "gradient":
        model = model.with_gradient()
    return model


@pytest.mark.parametrize("room", [False, True, "gradient"])
def test_the_consistency_maps_give_the_least_squares_residuals(room):
    """One product a sample (the deletion identity) gives what fitting every subset gives:
    chi2, the wrench, and chi2 with each chip left out, inf where the rest cannot see all
    axes (down to 2 chips: no degrees of freedom), for all chips and for subsets; with the
    gradient estimated, its whitened size."""
    model = packaged_model(room)
    rng = np.random.default_rng(11)
    for trial in range(60):
        chips = np.ones(8, dtype=bool)
        chips[rng.choice(8, trial % 7, replace=False)] = False
        b = model.zero + SIGMA_T * rng.normal(0, 1, 24) * rng.choice([1.0, 30.0])
        b[rng.integers(24)] += 40e-6  # one channel off: large drops, the culprit's above all
        c = model.consistency(b, SIGMA_T, chips)
        whole, wrench, without, gradient = _brute_force(model, b, SIGMA_T, chips)
        assert np.array_equal(np.isfinite(c.chi2_without), np.isfinite(without))
        if not np.isfinite(whole):
            assert not np.isfinite(c.chi2) and np.all(np.isnan(c.wrench))
            continue
        # Round-off: the sums are of whitened residuals, a few to thousands of sigma^2.
        assert c.chi2 == pytest.approx(whole, rel=1e-9, abs=1e-9)
        assert c.gradient_chi2 == pytest.approx(gradient, rel=1e-9, abs=1e-9)
        np.testing.assert_allclose(c.wrench, wrench, rtol=1e-8, atol=1e-12)
        finite = np.isfinite(without)
        np.testing.assert_allclose(
            c.chi2_without[finite], without[finite], rtol=1e-9, atol=1e-9 * (1 + whole)
        )
        np.testing.assert_allclose(
            c.drop, np.where(finite, c.chi2 - c.chi2_without, 0.0), atol=1e-9 * (1 + whole)
        )


def test_filtered_streams_restart_after_a_stall(tmp_path):
    """The loop stalled 1.5 s (SIGSTOP, a long pause) while the load changed by 2 N: the
    averaging and low-pass memory holds only samples from before the stall, so the first
    outputs after it would carry the old load unflagged. They restart on the fresh sample."""
    rig = Rig(tmp_path, extra="averaging = 4\nlowpass_hz = 10")
    rig.scene.set_load("sensor1", StaticLoad(np.zeros(6)))
    rig.cycles(100)
    rig.scene.set_load("sensor1", StaticLoad([2, 0, 0, 0, 0, 0]))  # within the calibrated loads
    d = rig.daemon
    deadline = rig.clock.now()
    rig.clock.wait_until(deadline + 1.5)
    deadline, lateness = d.timing.skip_missed(deadline, rig.clock.now(), d.period_s)  # as `Daemon.run`
    assert d.timing.missed >= 149
    after = rig.cycles(40)["wrench/sensor1"]
    settled = np.mean([s.values[0] for s in after[-10:]])
    assert abs(settled - 2) < 0.2  # the calibration reads the 2 N (within its error)
    # Every output after the stall is the new load, within noise (0.1 N: 4 sigma of a single
    # sample, the first output's, about 0.025 N), or flagged.
    wrong = [i for i, s in enumerate(after) if abs(s.values[0] - settled) > 0.1 and not s.flags]
    assert wrong == [], [round(after[i].values[0], 3) for i in wrong]
    assert not any(s.flags for s in after)  # none needed flagging: nothing of the past is left
    rig.close()


def _slow_reference(drops: list[list[float]], loads: list[float]) -> list[int | None]:
    """The slow test as it reads: every sample, each chip's drop summed over the window, against
    the limit at the window's largest load; the window starts again after a finding."""
    out: list[int | None] = []
    window: list[tuple[list[float], float]] = []
    for d, load2 in zip(drops, loads):
        window.append((d, load2))
        last = window[-SLOW_WINDOW:]
        if len(window) < SLOW_WINDOW:
            out.append(None)
            continue
        total = [sum(row[i] for row, _ in last) for i in range(len(d))]
        limit = _slow_limit(len(d), max(load2 for _, load2 in last))
        found = int(np.argmax(total)) if max(total) > limit**2 else None
        out.append(found)
        if found is not None:
            window = []
    return out


@settings(max_examples=200, deadline=None)
@given(
    st.lists(
        st.tuples(st.lists(st.floats(-1e-9, 40.0), min_size=8, max_size=8), st.floats(0.0, 0.3)),
        min_size=SLOW_WINDOW,
        max_size=4 * SLOW_WINDOW,
    )
)
def test_the_slow_tests_shortcut_finds_what_the_whole_sum_finds(samples):
    """The slow test skips the per-chip sum when the samples' largest drops add up to less than
    its least limit: it must find the same chips, on the same samples, as summing every time
    (drops up to 40 a sample: sums from far below to far beyond the limits, 233 at rest for 8
    chips; -1e-9: a drop's round-off below zero)."""
    check = RedundancyCheck()
    chips = every_chip(8)
    got = [
        check._slow_culprit(Consistency(0.0, 18, np.zeros(6), np.zeros(8), 15, np.array(d)), chips, 8, load2)
        for d, load2 in samples
    ]
    assert got == _slow_reference([d for d, _ in samples], [load2 for _, load2 in samples])


def test_the_slow_test_finds_a_chip_below_one_samples_limit():
    """A chip whose drop (25 a sample at rest) is a third of what one sample's test needs is
    found by the slow test on the window's 10th sample, not before."""
    check = RedundancyCheck()
    d = np.full(8, 2.0)
    d[3] = 25.0
    got = [
        check._slow_culprit(Consistency(0.0, 18, np.zeros(6), np.zeros(8), 15, d), every_chip(8), 8, 0.0)
        for _ in range(SLOW_WINDOW)
    ]
    assert got == [None] * (SLOW_WINDOW - 1) + [3]
