"""benchmarks/accuracy/coverage.py --quick: what it writes (every case at rest and under held
loads, at 1 and 2 sigma, with its sample counts, the commands, and the stamp's date and machine) and a figure
that could come out wrong: within 2 sigma is never fewer samples than within 1."""

from __future__ import annotations

import re

from benchmarks.accuracy import coverage as bench


def test_the_quick_coverage_benchmark_reports_every_case(regenerated):
    text = (regenerated / "coverage.md").read_text()
    assert text.startswith("# Each sample's sigma: coverage")
    assert "ftsensord dataset" in text and "ftsensord calibrate" in text
    assert "Made by `python -m benchmarks.accuracy.coverage --quick --parts " in text  # its own command
    # when and where: the stamp `benchmarks regenerate` writes, its last line
    assert re.search(r"\nGenerated on \d{4}-\d\d-\d\d by .* on a \d+-core [^\n]*\n$", text)
    percent = r"(\d+) %(?: \(x\))?"
    for case in bench.CASES:
        for load in ("rest", "held"):
            within = {}
            for k in (1, 2):
                found = re.search(
                    rf"\| {re.escape(case.name)} \| {load} \| (\d+) \| {k} sigma \| "
                    + r" \| ".join([percent] * 6),
                    text,
                )
                assert found, (case.name, load, k)
                assert int(found.group(1)) > 0  # samples with a sigma were read
                within[k] = [int(v) for v in found.groups()[1:]]
            assert all(two >= one for one, two in zip(within[1], within[2])), (case.name, load)


def test_the_quick_coverage_benchmark_names_its_conversions_and_compares_the_predicted_sigma(regenerated):
    """The conversion settings it ran (the packaged, shortest and longest) and, per case with
    every chip, the predicted sigma at rest against the measured one: six positive ratios."""
    text = (regenerated / "coverage.md").read_text()
    for name in bench.CONVERSIONS:
        assert re.search(rf"\| {name} \| OSR \d, DIG_FILT \d \| [\d.]+ ms \| [\d.]+ Hz \|", text), name
    ratio = r"(\d+\.\d\d)(?: \(x\))?"
    for case in bench.CASES:
        found = re.search(
            rf"\| {re.escape(case.name)} \| [^|]+ \| [^|]+ \| " + r" \| ".join([ratio] * 6) + r" \|", text
        )
        assert (found is None) == case.chip_out, case.name  # status predicts with every chip
        if found:
            assert all(float(v) > 0 for v in found.groups()), case.name
