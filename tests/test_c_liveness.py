"""The C client when the daemon is gone: fts_latest stops handing out the last sample as
live (FTS_E_STALE) once nothing new came for longer than its limit, and takes the samples
of a restarted daemon by itself; the example fails, saying so, when no sample ever came.

Built as tests/test_c_client.py builds them (its `tools` fixture)."""

from __future__ import annotations

import signal
import subprocess
import time

import pytest
import zmq

from .conftest import start_daemon
from .test_c_client import Driven, fields, frame, run, subscriptions, tools  # noqa: F401  (tools: the fixture)
from .test_daemon import write_config

FTS_E_ARG, FTS_E_STALE = "-3", "-15"
RATE_HZ = 100.0  # test_daemon's write_config default


def staleness(tools) -> dict[str, float]:
    return {k: float(v) for k, v in fields(run(tools.driver, "staleness")).items()}


def take_until_stale(c: Driven, deadline_s: float = 20.0) -> tuple[list[dict[str, str]], dict[str, str]]:
    """`take` until FTS_E_STALE: the replies before it, and it. The deadline only bounds a
    broken client's test (no assertion on time)."""
    before: list[dict[str, str]] = []
    end = time.monotonic() + deadline_s
    while time.monotonic() < end:
        got = c("take")
        if got["rc"] == FTS_E_STALE:
            return before, got
        before.append(got)
        time.sleep(0.002)  # a fast loop's tick, without spinning a core
    pytest.fail(f"no FTS_E_STALE within {deadline_s} s: last {before[-1]}")


@pytest.mark.parametrize("which", ["driver", "driver_cxx"])
def test_a_silent_stream_turns_stale_after_its_periods_and_a_new_sample_is_live_again(tools, tmp_path, which):
    const = staleness(tools)
    pub = zmq.Context.instance().socket(zmq.XPUB)
    endpoint = f"ipc://{tmp_path}/wrench"
    pub.bind(endpoint)
    c = Driven(getattr(tools, which), endpoint, "wrench/sensor1")
    try:
        # the wrench's subscription and its sigma's: a frame sent before its own is lost
        assert len(subscriptions(pub, 2)) == 2

        def publish(f: bytes) -> dict[str, str]:
            pub.send(f)
            return c("wait 5000")

        t0 = time.monotonic()
        first = publish(frame(seq=1, t_mono=t0))
        assert first["rc"] == "1" and float(first["limit"]) == const["first"]  # no period known yet
        # seq 2 skipped: the period is the stamps' difference over the sequence's.
        got = publish(frame(seq=3, t_mono=t0 + 0.04, values=[3.0] * 6))
        period = (t0 + 0.04 - t0) / 2
        assert got["rc"] == "1" and float(got["period"]) == period
        limit = max(const["periods"] * period, const["min"])
        assert float(got["limit"]) == limit and float(got["silent"]) == 0.0

        same, stale = take_until_stale(c)
        assert all(r["rc"] == "0" and float(r["silent"]) <= limit for r in same)  # live until the limit
        assert float(stale["silent"]) > limit
        assert (stale["seq"], stale["values"], stale["fresh"]) == ("3", got["values"], "0")  # r still filled
        assert c("take")["rc"] == FTS_E_STALE  # and stays so

        again = publish(frame(seq=4, t_mono=t0 + 0.06))
        assert (again["rc"], again["seq"], again["silent"]) == ("1", "4", "0")
        assert again["period"] == got["period"]  # kept until a span is complete
        # A span on from sample 1, its last stamp 5 ms late: averaged over the span, not the pair.
        spanned = publish(frame(seq=1 + int(const["span"]), t_mono=t0 + 0.325))
        assert float(spanned["period"]) == (t0 + 0.325 - t0) / const["span"]
        restarted = publish(frame(seq=0, t_mono=t0 + 0.34))  # a restart keeps the period known
        assert (restarted["rc"], restarted["restarted"], restarted["limit"]) == ("1", "1", spanned["limit"])
    finally:
        c.close()
        pub.close(linger=0)


def test_the_stale_limit_is_set_in_seconds_or_turned_off(tools, tmp_path):
    const = staleness(tools)
    pub = zmq.Context.instance().socket(zmq.XPUB)
    endpoint = f"ipc://{tmp_path}/wrench"
    pub.bind(endpoint)
    c = Driven(tools.driver, endpoint, "wrench/sensor1")
    try:
        assert len(subscriptions(pub, 2)) == 2  # the wrench's and its sigma's
        pub.send(frame(seq=1, t_mono=time.monotonic()))
        assert c("wait 5000")["rc"] == "1"
        assert c("stale 0.25")["rc"] == "0" and float(c("take")["limit"]) == 0.25
        same, stale = take_until_stale(c)
        assert all(float(r["silent"]) <= 0.25 for r in same) and float(stale["silent"]) > 0.25

        assert c("stale -1")["rc"] == "0"  # FTS_STALE_NEVER: the old behaviour, on request
        never = c("take")  # silent past the limit that just made it stale, yet FTS_SAME
        assert (never["rc"], float(never["limit"]) < 0) == ("0", True) and float(never["silent"]) > 0.25
        assert c("stale 0")["rc"] == "0" and float(c("take")["limit"]) == const["first"]  # the default back
        assert c("stale nan")["rc"] == FTS_E_ARG and float(c("take")["limit"]) == const["first"]
    finally:
        c.close()
        pub.close(linger=0)


def test_a_killed_daemon_is_reported_stale_and_its_restart_flows_again(tools, tmp_path):
    const = staleness(tools)
    config = write_config(tmp_path, rate_hz=RATE_HZ)
    proc, notify = start_daemon(config, tmp_path)
    endpoint = f"ipc://{tmp_path / 'ftsensord' / 'wrench'}"
    c = Driven(tools.driver, endpoint, "wrench/sensor1")
    try:
        live = first = c("wait 10000")
        # Two spans: the period is an average, and a restart's numbering goes back.
        while int(live["seq"]) < int(first["seq"]) + 2 * const["span"]:
            live = c("wait 10000")
        assert live["rc"] == "1"
        proc.kill()
        proc.wait()
        same, stale = take_until_stale(c)
        limit = float(stale["limit"])
        # The daemon stamps each cycle on its schedule; over a span a late stamp moves the
        # average by its delay over the span, far less than half a period.
        assert 0.5 / RATE_HZ < float(stale["period"]) < 1.5 / RATE_HZ, stale
        assert limit == max(const["periods"] * float(stale["period"]), const["min"])
        assert float(stale["silent"]) > limit and all(
            float(r["silent"]) <= limit for r in same if r["rc"] == "0"
        )
        assert int(stale["seq"]) >= int(live["seq"])  # the last sample, still handed out with the code

        notify.close()
        (tmp_path / "notify").unlink()
        proc, notify = start_daemon(config, tmp_path)
        back = c("wait 30000")  # the client reconnects by itself
        assert (
            back["rc"] == "1" and back["restarted"] == "1" and float(back["t_mono"]) > float(stale["t_mono"])
        )
        assert c("wait 5000")["rc"] == "1"  # and samples flow again
    finally:
        c.close()
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=10)
        notify.close()


def test_the_example_fails_saying_so_when_no_sample_came(tools, tmp_path):
    endpoint = f"ipc://{tmp_path}/nothing-here"
    for args in (["-s", "0.5"], ["-w", "0.5"]):  # the run ends, or its wait for a first sample does
        done = subprocess.run(
            [str(tools.example), "-e", endpoint, "-t", "wrench/sensor1", *args],
            capture_output=True,
            text=True,
            timeout=30,
            check=False,
        )
        assert done.returncode == 1, (args, done.returncode, done.stderr)
        assert endpoint in done.stderr and "wrench/sensor1" in done.stderr and "no sample" in done.stderr, (
            done.stderr
        )
        assert "new samples 0" in done.stdout.splitlines()[-1]
