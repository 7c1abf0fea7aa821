"""benchmarks/accuracy/accuracy.py --quick: the structure of what it writes (sections, sensors,
counts of loads and fall-backs), not its figures, which docs/results/accuracy-figures.md holds."""

from __future__ import annotations

import re


def test_the_quick_accuracy_benchmark_reports_every_section_and_count(regenerated):
    text = (regenerated / "accuracy-figures.md").read_text()
    for section in (
        "## As-built sensors in the Earth's field",
        "## Ablation (seed 1): which effect costs what",
    ):
        assert section in text
    assert (
        "10 loads of 100 g (100 readings" in text
        and "10 large loads" in text
        and "Sensors: seeds 1, 2." in text
    )
    # Both classes for both estimators, with a spread across the sensors.
    for kind in ("100 g", "large"):
        for estimator in ("linear", "nonlinear"):
            assert re.search(rf"\| {kind} \| {estimator} \| [\d.e+-]+ \+- ", text), (kind, estimator)
    # Fall-backs counted per sensor and class, out of the loads used.
    assert len(re.findall(r"\| seed \d \| [\d.]+ \| \d+ of 10 \| \d+ of 10 \| \d+ \| \d+ \|", text)) == 2
    ablation = (
        "nominal, field-free",
        "nominal, Earth's field",
        "as-built, field-free",
        "as-built, Earth's field",
        "as-built, Earth's field, dipole model",
        "as-built, Earth's field, test readings noiseless",
    )
    for name in ablation:
        assert text.count(f"| {name} | ") == 5  # 2 classes x 2 estimators, and its fall-backs
    assert "Scene: the default's room and part" in text and "after a tare of 100 readings" in text
    sweep = text.split("No-load sweep")[1].split("## Ablation")[0]
    for readings in ("100 readings", "16 readings", "noiseless"):
        for estimator in ("linear", "nonlinear"):  # the mean across sensors, the largest in brackets
            assert re.search(rf"\| {estimator}, {readings} \| [\d.e+-]+ \([\d.e+-]+\) \|", sweep), (
                estimator,
                readings,
            )
