"""The speed/accuracy benchmark's quick mode runs in CI (its figures live in docs/tradeoff.md)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path


def test_quick_tradeoff_produces_every_section():
    script = Path(__file__).resolve().parent.parent / "benchmarks" / "tradeoff.py"
    out = subprocess.run([sys.executable, str(script), "--quick"], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    text = out.stdout
    for heading in ("## Rate", "## Accuracy", "## The Pareto front", "## Cost and latency"):
        assert heading in text
    assert re.search(r"\| 1, 2 \| 835 \| 14\.9 / [\d.]+ \| 124\.3 / [\d.]+ \|", text)  # bounds as computed
    assert text.count("| nonlinear |") == 4 and text.count("| linear |") == 4
    assert "Recommended for 100 Hz" in text or "reaches 100 Hz" not in text
