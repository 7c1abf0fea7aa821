"""benchmarks/performance/latency_sub.c, the C subscribers of benchmarks/performance/latency.py: built as
clients/c/build.py builds the example, fed known frames over a real ipc socket, it must
report every sample after its settle time once per subscriber, with the sample's own
sequence number and its age at receipt."""

from __future__ import annotations

import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
import zmq

from ftsensord.protocol import wire

from .test_c_client import build  # clients/c/build.py, loaded once

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def program(tmp_path_factory):
    if build.compiler("c") is None:
        pytest.skip("no C compiler")
    try:
        libzmq = build.find_libzmq()
    except LookupError as exc:
        pytest.skip(str(exc))
    out = tmp_path_factory.mktemp("latency_sub") / "latency_sub"
    build.build([ROOT / "benchmarks" / "performance" / "latency_sub.c"], out, "c", libzmq)
    return out


@pytest.mark.parametrize("shared", [False, True])
def test_every_subscriber_reports_each_sample_with_its_age(program, tmp_path, shared):
    ctx = zmq.Context.instance()
    pub = ctx.socket(zmq.PUB)
    endpoint = f"ipc://{tmp_path / 'wrench'}"
    pub.bind(endpoint)
    settle, seconds = 0.3, 0.6
    proc = subprocess.Popen(
        [
            str(program),
            endpoint,
            "wrench/sensor1",
            "3",
            str(settle),
            str(seconds),
            *(["shared"] if shared else []),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    ages = 0.002  # each sample's t_mono this long before its send: the age the program must report at least
    sent = []
    try:
        start = time.monotonic()
        seq = 0
        while time.monotonic() - start < settle + seconds + 0.2:
            t = time.monotonic()
            for topic in ("wrench/sensor2", "wrench/sensor1"):  # another topic: not counted
                pub.send(wire.encode(topic, wire.KIND_WRENCH, seq, t - ages, 0.0, 0, np.zeros(6)))
            sent.append((seq, t - ages))
            seq += 1
            time.sleep(0.01)
        out, err = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
        pub.close(linger=0)
    assert proc.returncode == 0, err
    rows = np.array([[int(v) for v in line.split()] for line in out.splitlines()])
    seqs, delays_s = rows[:, 0], rows[:, 1] * 1e-9
    # Every counted sample reached all three subscribers, once each (the first and the last
    # may straddle the settle's or the run's end: some subscribers took them, others not).
    counts = np.bincount(seqs)[seqs.min() + 1 : seqs.max()]
    assert len(counts) >= 20 and set(counts) == {3}
    # Counted from the settle on (by the sample's t_mono against the program's start), ...
    first_counted = dict(sent)[int(seqs.min())]
    assert first_counted - start >= settle - 0.1  # the program started up to 0.1 s after `start`
    # ... with an age at receipt of at least the age it was sent with, and not much more.
    assert delays_s.min() >= ages and np.median(delays_s) < ages + 0.05
    assert "subscribers 3" in err and f"receipts {len(rows)}" in err
