"""benchmarks/performance/ros2_latency.py's ``--alone`` without timing anything: which subscriber each
variant's segment runs, the configuration its daemon gets, and how a DDS variant's p99 is
set against ZeroMQ's, round by round (its figures live in docs/results/performance.md)."""

from __future__ import annotations

from pathlib import Path

import pytest

from benchmarks.performance import ros2_latency as bench
from ftsensord.config.file import load_config


def test_alone_runs_one_subscriber_a_segment_the_one_its_name_says():
    chosen = {}
    for variant, names in bench.ALONE.items():
        assert len(names) == 1, variant  # one process woken a sample: none competes with another
        (p,) = [bench.listener(n, Path("/nowhere"), 0.0, None) for n in names]
        chosen[variant] = (p._target.__name__, p._args[1] if p._target is bench.dds_listen else None)
    assert chosen == {
        "none": ("zmq_listen", None),
        "zmq-alone": ("zmq_listen", None),
        "dds-be-alone": ("dds_listen", False),
        "dds-rel-alone": ("dds_listen", True),
    }


def test_alone_daemons_run_the_in_loop_output_but_none(tmp_path):
    pytest.importorskip("cyclonedds")  # a [ros2] table needs the extra to load
    for variant in bench.ALONE:
        config = load_config(bench.segment_config(variant, tmp_path / f"{variant}.toml"))
        assert (config.ros2.output if config.ros2 else None) == (None if variant == "none" else "in-loop"), (
            variant
        )


def _segment(variant: str, t0: float, delay_s: float, name: str = "x") -> dict:
    """A segment counting [t0, t0 + 10) with 100 receipts ``delay_s`` after their stamps, and
    five stamped before the window (its settling) whose delay, 10 s, would rule every p99 if
    they were counted."""
    got = [(t0 - 10.0 + i, t0 + i) for i in range(5)] + [
        (t0 + i * 0.01, t0 + i * 0.01 + delay_s) for i in range(100)
    ]
    return {"variant": variant, "window": (t0, t0 + 10.0), "receipts": {name: got}}


def test_dds_p99_is_set_against_the_zeromq_segment_of_its_own_round():
    # round 1: ZeroMQ 1 ms, DDS 3 ms; round 2: ZeroMQ 2 ms, DDS 2.5 ms (in the order main runs them)
    segments = [
        _segment("zmq-alone", 0, 1e-3, "zmq"),
        _segment("dds-be-alone", 20, 3e-3),
        _segment("zmq-alone", 40, 2e-3, "zmq"),
        _segment("dds-be-alone", 60, 2.5e-3),
    ]
    pooled, by_round = bench.p99_above(segments, "dds-be-alone", "zmq-alone")
    assert by_round == pytest.approx([2000.0, 500.0])  # not +1500 and +1000: rounds crossed
    # pooled: p99 of 3 and 2.5 ms (3 ms, half of them) minus p99 of 1 and 2 ms (2 ms)
    assert pooled == pytest.approx(1000.0)
