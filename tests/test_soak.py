"""The soak benchmark's quick mode: random scripted faults for 15 s against a real daemon.
It checks survival, flagging and that no unflagged sample is wrong; the timing figures
live in docs/results/reliability.md."""

from __future__ import annotations

import numpy as np

from ftsensord.config.file import builtin_path, load_config
from ftsensord.sim import load_scene


def test_quick_soak_survives_flags_and_lets_no_wrong_sample_through():
    from benchmarks.robustness import soak

    report = soak.soak(0.25, seed=3, per_minute=30)
    assert report["alive_at_end"] and report["exit_code"] == 0
    assert report["faults_injected"] >= 3
    assert sum(report["flagged"].values()) > 0  # the faults showed in the samples
    # A subscriber that keeps up misses nothing but the cycles the loop skipped (a busy
    # machine's, counted by status from before it subscribed: each is a sequence jump).
    assert all(g <= report["missed_cycles"] for g in report["sequence_gaps"].values()), (
        report["sequence_gaps"],
        report["missed_cycles"],
        report["skipped_deadlines_seen"],
    )
    assert min(report["samples"].values()) > 0.5 * 15 * 100  # the loop kept publishing
    wrong = report["wrong_samples"]
    for topic, s in wrong["per_stream"].items():
        assert s["reference_from"] > 100, topic  # the truth and the noise from enough quiet samples
        # The measured noise is the chips' (the daemon's own model of it), not a fault's spread.
        ratio = np.array(s["sigma_measured"]) / np.array(s["sigma_predicted"])
        assert np.all((ratio > 0.67) & (ratio < 1.5)), (topic, ratio)
    # Under the static load a fault's samples are flagged and, estimated from the chips left,
    # mostly right; a chip trusted too early after a reset, a wrong subset map or a filter
    # carrying a fault's values would show here.
    # A sample beyond 5 sigma whose chips all read within their noise is the noise's
    # (docs/results/reliability.md, "Noise tails"); one with a chip beyond is wrong, never allowed.
    assert wrong["unflagged_wrong"] == 0, wrong["wrong"]
    assert wrong["made_by_noise"] + wrong["unflagged_wrong"] == wrong["unflagged_beyond_5_sigma"]


def test_a_wrong_sample_is_told_from_noise_by_its_chips(tmp_path):
    """soak.wrong_samples on made-up streams: a wrench beyond 5 sigma whose chips all read
    within their noise is the noise's; one with a chip off, or with no flux to tell, is wrong."""
    from benchmarks.robustness import soak

    config = load_config(builtin_path("sim.toml"))
    (tmp_path / "scene.toml").write_text(soak.scene_text([]))
    rng = np.random.default_rng(0)
    n = 3000
    samples = {
        t: [(i, i * 0.01, 0) for i in range(n)]
        for t in ("wrench/sensor1", "wrench/sensor2", "wrench/tip", "flux/sensor1", "flux/sensor2")
    }
    values = {t: list(rng.normal(0.0, 1.0, (n, 24 if t.startswith("flux/") else 6))) for t in samples}
    for t in ("wrench/sensor2", "wrench/tip"):
        values[t][1000] = values[t][1000] + [8.0, 0, 0, 0, 0, 0]  # chip 3 of sensor2 read a wrong field:
    values["flux/sensor2"][1000][9] += 12.0
    values["wrench/sensor2"][1500][5] += 8.0  # every chip within its noise
    values["wrench/sensor1"][2000][0] -= 8.0  # and no flux for it at all
    del samples["flux/sensor1"][2000], values["flux/sensor1"][2000]
    out = soak.wrong_samples(
        samples, values, [], config, load_scene(tmp_path / "scene.toml"), tail_samples=1000
    )
    wrong = {(w["stream"], w["seq"]): w["chips_beyond_noise"] for w in out["wrong"]}
    assert wrong[("wrench/sensor2", 1000)] == ["sensor2/chip3"]
    assert wrong[("wrench/tip", 1000)] == ["sensor2/chip3"]
    assert wrong[("wrench/sensor2", 1500)] == ["none: made by noise"]
    assert wrong[("wrench/sensor1", 2000)] == ["sensor1/chip-1"]
    per = out["per_stream"]
    assert (per["wrench/sensor2"]["unflagged_wrong"], per["wrench/sensor2"]["made_by_noise"]) == (1, 1)
    assert out["unflagged_wrong"] == 3 and out["made_by_noise"] == 1
