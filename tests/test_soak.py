"""The soak benchmark's quick mode: random scripted faults for 15 s against a real daemon.
It checks survival and flagging only; the timing figures live in docs/reliability.md."""

from __future__ import annotations

import importlib.util
from pathlib import Path


def test_quick_soak_survives_flags_and_loses_no_sample():
    path = Path(__file__).resolve().parent.parent / "benchmarks" / "soak.py"
    spec = importlib.util.spec_from_file_location("soak", path)
    soak = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(soak)
    report = soak.soak(0.25, seed=3, per_minute=30)
    assert report["alive_at_end"] and report["exit_code"] == 0
    assert report["faults_injected"] >= 3
    assert sum(report["flagged"].values()) > 0  # the faults showed in the samples
    assert report["sequence_gaps"] == {}  # a subscriber that keeps up missed nothing
    assert min(report["samples"].values()) > 0.5 * 15 * 100  # the loop kept publishing
