"""The speed/accuracy benchmark: its quick mode runs in CI (its figures live in
docs/results/tradeoff.md), and its no-truth path (a real bus) is checked on a static scene."""

from __future__ import annotations

import math
import re

from benchmarks.accuracy import tradeoff as bench
from ftsensord.chip import mlx90393 as mlx
from ftsensord.config.file import builtin_path, load_config
from ftsensord.sim import two_sensor_scene


def test_quick_tradeoff_produces_every_section(regenerated):
    text = (regenerated / "tradeoff.md").read_text()
    for heading in ("## Rate", "## Accuracy", "## The Pareto front", "## Cost and latency"):
        assert heading in text
    # Bounds as computed for the default (Pi 4) adapter: naive 14.5, overlapped 116.2, burst 176.4 Hz.
    assert re.search(r"\| 1, 2 \| 835 \| 14\.5 / [\d.]+ \| 116\.2 / [\d.]+ \| .* \| 176\.4 / [\d.]+ \|", text)
    assert text.count("| nonlinear |") == 4 and text.count("| linear |") == 4
    # A verdict either way: which one is the measured rates' (a loaded host's may reach none).
    assert ("**Recommended for 100 Hz with 16 chips**" in text) != (
        "No setting measured reaches 100 Hz" in text
    )


def test_pareto_keeps_only_points_nothing_beats():
    points = [
        (100, 0.5, "a"),
        (50, 0.2, "b"),
        (100, 0.6, "beaten by a"),
        (40, 0.3, "beaten by b"),
        (200, 1, "c"),
    ]
    assert sorted(p[2] for p in bench.pareto(points)) == ["a", "b", "c"]


def test_a_bus_without_truth_gives_noise_and_no_rmse(tmp_path):
    """On a bus with no loads to set (a real one, here a static scene) the benchmark
    measures noise at rest and leaves the truth columns empty instead of inventing them."""
    truth = two_sensor_scene()
    chips = "".join(
        f"[[chip]]\naddress = {a}\nfield_ut = {[float(v) for v in truth.field_t(a, 0.0) * 1e6]}\n"
        for a in range(0x0C, 0x14)
    )
    (tmp_path / "scene.toml").write_text(f'version = 1\nkind = "static"\n{chips}')
    (tmp_path / "cfg.toml").write_text(
        f'version = 1\nbus = "sim:scene.toml"\n[[sensor]]\nname = "s"\naddresses = {list(range(0x0C, 0x14))}\n'
        f'calibration = "{builtin_path("sim-sensor1.json")}"\n'
    )
    config = load_config(tmp_path / "cfg.toml")
    rows = bench.accuracy(config, mlx.Settings(), 1, 2)
    assert [r.estimator for r in rows] == ["linear", "nonlinear"]
    with_truth = bench.accuracy(load_config(builtin_path("sim.toml")), mlx.Settings(), 1, 1)
    for r, t in zip(rows, with_truth):
        # The same chips' noise through the same model: the same RMS to sampling error (120 samples: ~7 %).
        assert 0.7 < r.noise_n / t.noise_n < 1.4 and 0.7 < r.noise_nm / t.noise_nm < 1.4
        assert math.isnan(r.rmse_cal) and math.isnan(r.rmse_large) and not math.isnan(t.rmse_cal)
    rates = {(1, 2, s): (124.0, 120.0) for s in ("naive", "overlapped", "burst")}
    text = bench.render(
        config,
        [(1, 2)],
        rates,
        rows,
        {"linear": 300.0, "nonlinear": 1500.0},
        (300.0, 800.0, 900.0),
        True,
        1.0,
    )
    assert "noise F at rest" in text and "RMSE cal. range (N) | RMSE large" in text
    assert "| - | - | - | - |" in text and "nan" not in text
