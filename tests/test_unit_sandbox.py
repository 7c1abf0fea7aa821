"""The daemon under its own systemd unit's restrictions (benchmarks/robustness/unit_sandbox.py): the
system call filter installed with seccomp before exec, the unit's limits, and the real-time
priority its ExecStart= asks for. `systemd-analyze verify` and `security` (tests/test_service.py) read the unit; only
running the program under it shows whether the program survives it: libzmq's threads call
pthread_setschedparam at start and abort when the filter refuses it."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from benchmarks.robustness import hostile
from benchmarks.robustness import unit_sandbox as sandbox
from ftsensord.client import ControlClient, Subscriber

from .conftest import start_daemon
from .test_daemon import write_config

UNIT = Path(__file__).resolve().parent.parent / "systemd" / "ftsensord.service"

pytestmark = pytest.mark.skipif(
    not sandbox.seccomp_available() and not os.environ.get("CI"),
    reason="seccomp is unavailable here (never skipped in CI)",
)


@pytest.fixture(scope="module")
def unit():
    return sandbox.UnitRestrictions.from_unit(UNIT)


def run_child(code: str, preexec) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", code], preexec_fn=preexec, capture_output=True, text=True, timeout=60
    )


def test_the_sandbox_filters_what_the_unit_denies(unit):
    """The filter is real: a call of @privileged (sethostname) and one of @resources that
    the unit does not give back (setpriority) fail with the unit's EPERM; the daemon's own
    calls pass."""
    allowed = unit.allowed_calls(sandbox.syscall_groups())
    assert allowed is not None and "sethostname" not in allowed and "setpriority" not in allowed
    assert {"read", "epoll_wait", "ioctl", "openat"} <= allowed
    code = (
        "import errno, os, socket\n"
        "for f in (lambda: socket.sethostname('x'), lambda: os.setpriority(os.PRIO_PROCESS, 0, 1)):\n"
        "    try:\n        f()\n        print('allowed')\n"
        "    except PermissionError:\n        print('EPERM')\n"
    )
    out = run_child(code, unit.preexec())
    assert out.returncode == 0 and out.stdout.split() == ["EPERM", "EPERM"], out.stderr
    # Without the filter the same child is refused sethostname for want of the capability
    # only if it is not root; setpriority(1) (nicer) is always allowed: the EPERM above is the filter's.
    plain = run_child("import os; os.setpriority(os.PRIO_PROCESS, 0, 1); print('ok')", None)
    assert plain.stdout.strip() == "ok"


def test_pyzmq_survives_the_filter(unit):
    """A bare ZeroMQ context and socket: libzmq's I/O thread sets its scheduling parameters
    when it starts, and aborts (exit 134) if the filter refuses sched_setscheduler."""
    out = run_child(
        "import zmq; c = zmq.Context(); s = c.socket(zmq.PUB); s.bind('inproc://x'); "
        "s.close(); c.term(); print('ok')",
        unit.preexec(),
    )
    assert out.returncode == 0 and out.stdout.strip() == "ok", (out.returncode, out.stderr[-500:])


def test_the_daemon_runs_under_its_own_unit(tmp_path, unit):
    """Ready, publishing, status, tare, reload (SIGHUP) and a clean stop, all under the
    unit's filter, limits and policy."""
    config = write_config(tmp_path)
    proc, notify = start_daemon(
        config,
        tmp_path,
        args=unit.run_args,
        preexec_fn=unit.preexec(),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    try:
        folder = tmp_path / "ftsensord"
        control = ControlClient(f"ipc://{folder / 'control'}")
        status = control.status()
        assert status["rate_hz"] > 0
        # The daemon asked for SCHED_FIFO itself (the unit's `--realtime`): granted under the
        # unit's LimitRTPRIO= (or to root), said in status; the loop's thread and libzmq's
        # (made after the request: they inherit it) have it. numpy's BLAS worker, made at
        # import, does not: small products never wake it.
        assert unit.realtime and unit.limit_rtprio >= unit.realtime
        assert status["scheduling"] == {
            "policy": "fifo",
            "priority": unit.realtime,
            "asked": unit.realtime,
            "refused": None,
        }, status["scheduling"]
        tasks = {
            int(t): Path(f"/proc/{proc.pid}/task/{t}/comm").read_text().strip()
            for t in os.listdir(f"/proc/{proc.pid}/task")
        }
        zmq_threads = [t for t, name in tasks.items() if name.startswith("ZMQbg/")]
        assert len(zmq_threads) >= 2, tasks  # its I/O thread and reaper
        for task in [proc.pid, *zmq_threads]:
            assert os.sched_getscheduler(task) == os.SCHED_FIFO, tasks[task]
        with Subscriber(f"ipc://{folder / 'wrench'}", ["wrench/sensor2"]) as sub:
            sample = sub.receive(timeout_s=5)
            assert sample is not None and np.all(np.isfinite(sample.values))
        assert np.all(np.isfinite(control.tare(samples=100, sensor="sensor2")["tare_wrench"]["sensor2"]))
        with Subscriber(f"ipc://{folder / 'wrench'}", ["wrench/sensor2"]) as sub:
            tared = np.array([sub.receive(timeout_s=5).values for _ in range(100)])
        # Zeroed: two means of 100 samples (the tare's and these) at about 0.02 N a sample
        # differ by 0.003 N (one sigma); 0.02 N is 7 sigma (20 samples once gave 0.024 N).
        assert np.all(np.abs(tared.mean(axis=0)[:3]) < 0.02), tared.mean(axis=0)
        cycles = status["cycles"]
        proc.send_signal(signal.SIGHUP)
        assert control.status()["cycles"] > cycles  # still cycling and answering after the reload
        proc.send_signal(signal.SIGTERM)
        output = proc.communicate(timeout=20)[0]
        assert proc.returncode == 0, output[-2000:]
        assert "Operation not permitted" not in output, output[-2000:]
    finally:
        if proc.poll() is None:
            proc.kill()
        notify.close()


@pytest.mark.skipif(
    sandbox.shutil.which("systemd-analyze") is None, reason="no systemd here to compare the copy with"
)
def test_the_groups_copy_matches_this_hosts_systemd():
    """The copy used where systemd is missing expands the unit's groups as this host's does."""
    copy = sandbox.parse_groups(sandbox.GROUPS_FALLBACK.read_text())
    live = sandbox.syscall_groups()
    for group in ("@system-service", "@privileged", "@resources", "@default"):
        assert sandbox.expand([group], copy) == sandbox.expand([group], live), group


@pytest.fixture
def memory_group(unit):
    """A memory cgroup limited to the unit's MemoryMax=, or None where this host lets us make
    none (then the daemon's peak RSS stands in for what the cgroup counts)."""
    group = sandbox.MemoryGroup.make(unit.memory_max, f"ftsensord-test-{os.getpid()}")
    yield group
    if group is not None:
        group.remove()


@pytest.fixture
def sandboxed_daemon(tmp_path, unit, memory_group):
    """The packaged simulated daemon under the unit's restrictions, in ``memory_group``;
    its runtime folder."""
    config = hostile.packaged_config(tmp_path / "ftsensord.toml")
    proc, notify = hostile.sandboxed(config, tmp_path, unit, memory_group)
    try:
        yield proc, tmp_path / "ftsensord"
    finally:
        code = hostile.stop(proc, notify)
        assert code == 0, (tmp_path / "daemon.log").read_text()[-2000:]


def assert_within_memory_max(unit, memory_group, out: dict) -> None:
    """The daemon stayed under the unit's MemoryMax=: counted and enforced by the kernel in
    its cgroup where there is one (never OOM-killed, its peak below), else by its peak RSS."""
    assert unit.memory_max is not None
    assert out["rss_peak_mib"] * 2**20 < unit.memory_max, out
    if memory_group is None:
        return
    assert memory_group.oom_kills() == 0, out
    # The kernel holds a group's peak at its limit (reclaiming, then killing), so the peak is
    # held to three quarters of it: the worst hostile load measured 146 of 256 MiB.
    peak = memory_group.peak()
    assert peak is None or peak < 0.75 * unit.memory_max, (peak, out)


def test_the_memory_group_enforces_its_limit(tmp_path, unit):
    """The cgroup the tests use is enforced here, so a daemon within it is within the unit's
    MemoryMax=: the same daemon in a group of 16 MiB (it charges about 28 of its own) is OOM-killed."""
    # Out of swap too: with swap, a process over the limit is swapped out rather than killed.
    group = sandbox.MemoryGroup.make(16 * 2**20, f"ftsensord-small-{os.getpid()}", swap=False)
    if group is None:
        pytest.skip("no memory cgroup without swap can be made here (no memory controller delegated to us)")
    try:
        config = hostile.packaged_config(tmp_path / "ftsensord.toml")
        out = subprocess.run(
            [sys.executable, "-m", "ftsensord", "run", "--config", str(config), *unit.run_args],
            env={**os.environ, "XDG_RUNTIME_DIR": str(tmp_path)},
            capture_output=True,
            preexec_fn=unit.preexec(memory=group),
            timeout=60,
        )
        assert out.returncode == -signal.SIGKILL, out.stderr[-2000:]
        assert group.oom_kills() >= 1
    finally:
        group.remove()


def test_connections_beyond_the_unit_descriptor_limit_are_refused_not_fatal(sandboxed_daemon, unit):
    """1200 connections held on each of control and wrench, more than the unit's soft
    limit (1024, or systemd's default without LimitNOFILE=): libzmq aborts on EMFILE in
    its ipc listener, so the daemon must keep its descriptors far below the limit."""
    proc, folder = sandboxed_daemon
    out = hostile.descriptors(folder, proc, 1200)
    assert out["alive"], out
    # Every connection reached the daemon's accept (2400, past its soft limit of 1024):
    # a connect waits while the backlog is full rather than being refused by the kernel.
    assert out["refused_by_kernel"] == 0, out
    for cap in out["status_connections"].values():
        assert cap["peak"] <= cap["limit"] and cap["refused"] > 0, out
    # Descriptors: the caps (128 each), about 30 of the daemon's own, and what a burst brings
    # before the next drain (this side connects about 8000 a second: 80 a cycle, more when a
    # cycle is late; 512 was seen once in 8 runs). Below 768 keeps a quarter of the unit's
    # soft limit (1024) spare; the daemon itself raises its limit to the hard one (16384).
    assert out["daemon_fds_most"] < 768, out
    # The surplus shut down at once, the silent ones after the handshake timeout: all of
    # them, however the split between the two fell (it depends on how fast this side connects).
    assert out["closed_by_daemon"] == 2 * 1200, out


def test_clients_that_never_read_have_their_replies_dropped(sandboxed_daemon, unit, memory_group):
    """20 clients each send 300 `status` requests and read nothing: each pins at most
    REPLY_HWM replies (128, about 700 KB), the rest are dropped and counted; memory comes back."""
    proc, folder = sandboxed_daemon
    out = hostile.unread(folder, proc, clients=20, requests=300)
    assert out["alive"]
    # Each client: 300 replies, 128 queued in the daemon and some more in transit (the
    # kernel's socket buffer, the client's queue of 1: 26-42 measured): 100 a client at least dropped.
    assert out["replies_dropped"] >= 20 * 100, out
    # 20 x 128 replies of 5.4 KB is 13.8 MB; 20 MB leaves room for the allocator's
    # granularity, against the 32 MB the default 1000-reply queues pin.
    assert out["rss_loaded_mib"] - out["rss_before_mib"] < 20, out
    # Given back once they left (malloc_trim): at least half of what they took (before: 1 %).
    assert out["rss_after_mib"] - out["rss_before_mib"] < 0.5 * (
        out["rss_loaded_mib"] - out["rss_before_mib"]
    ), out
    assert_within_memory_max(unit, memory_group, out)


def test_subscribers_that_never_read_cost_little_and_no_sample_of_a_reader(
    sandboxed_daemon, unit, memory_group
):
    """127 subscribers of every stream that read nothing fill their queues in the daemon
    (1000 messages each) beside one recorder that reads: it loses nothing, the daemon's
    memory grows by about 80 KB a stalled subscriber and comes back when they leave."""
    proc, folder = sandboxed_daemon
    out = hostile.stalled(folder, proc, clients=127, seconds=5)
    assert out["alive"] and out["publish_connections_refused"] == 0, out
    assert out["recorder_received"] > 0.9 * 5 * 100 * 5, out  # five streams at 100 Hz
    assert all(g <= out["missed_cycles"] for g in out["recorder_gaps"].values()), out
    # 9.7 MiB measured for 127 (docs/results/reliability.md): 16 MiB is room for the allocator's
    # granularity, against 127 x 1000 messages of 150-250 bytes copied (about 25 MiB).
    assert out["rss_loaded_mib"] - out["rss_before_mib"] < 16, out
    assert out["rss_after_mib"] - out["rss_before_mib"] < 0.5 * (
        out["rss_loaded_mib"] - out["rss_before_mib"]
    ), out
    assert_within_memory_max(unit, memory_group, out)
