"""`ftsensord bridge` against `ftsensord run` on the simulated bus, read by Foxglove's own
client libraries: tests/foxglove_client/check.mjs, node running `@foxglove/ws-protocol`'s
FoxgloveClient (over `ws`) and decoding with `@foxglove/rosmsg` + `@foxglove/rosmsg2-serialization`,
the versions pinned by its package-lock.json (installed here with `npm ci` when missing).
Checked sample by sample against a Python `Subscriber` receiving in parallel.

Without node or npm (or with no registry to install from) the tests skip, saying why; with
the environment variable CI set they fail instead: CI must run them."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from ftsensord.client import ControlClient
from ftsensord.recording.ros2mcap import STATUS, WRENCH, stamp

from .conftest import StreamRecorder, start_daemon
from .test_daemon import write_config

pytest.importorskip("foxglove")  # the live extra, which the test extra includes

CLIENT = Path(__file__).resolve().parent / "foxglove_client"
STREAMS = ["wrench/sensor1", "wrench/tip"]
SCHEMAS = {**{f"/{s}": WRENCH for s in STREAMS}, **{f"/{s}/status": STATUS for s in STREAMS}}
COUNT = 200  # messages: 50 samples a stream (a wrench and its status each), 0.5 s at 100 Hz


def missing(reason: str) -> None:
    """Skip for want of the client's tools, except in CI, which must run these tests."""
    if os.environ.get("CI"):
        pytest.fail(f"{reason} (CI is set: the Foxglove client test must run)")
    pytest.skip(reason)


def installed(package: str) -> str | None:
    """The version of ``package`` in the client's node_modules, None if absent."""
    manifest = CLIENT / "node_modules" / package / "package.json"
    return json.loads(manifest.read_text())["version"] if manifest.exists() else None


@pytest.fixture(scope="session")
def check_mjs() -> list[str]:
    """The command that runs the Foxglove client (``node check.mjs``), its packages installed
    from the committed lock file first if any is missing or not the version package.json pins."""
    node, npm = shutil.which("node"), shutil.which("npm")
    if node is None or npm is None:
        missing("the Foxglove client test needs node (>= 20) and npm on PATH")
    assert node is not None and npm is not None
    version = subprocess.run([node, "--version"], capture_output=True, text=True, check=True).stdout.strip()
    if int(version.lstrip("v").split(".")[0]) < 20:  # @foxglove/rosmsg2-serialization's engines: node >= 20
        missing(f"the Foxglove client test needs node >= 20, not {version}")
    pinned = json.loads((CLIENT / "package.json").read_text())["dependencies"]
    if any(installed(name) != want for name, want in pinned.items()):
        done = subprocess.run(
            [npm, "ci", "--no-audit", "--no-fund"], cwd=CLIENT, capture_output=True, text=True, timeout=600
        )  # a slow registry mirror, not a hang
        if done.returncode != 0:
            missing(f"npm ci in {CLIENT} failed: {(done.stderr or done.stdout).strip()[-600:]}")
    return [node, str(CLIENT / "check.mjs")]


def Reference(endpoint: str) -> StreamRecorder:  # noqa: N802 (a class's name to its callers)
    """Every sample of the streams, by (topic, seq), as the Python client receives them."""
    return StreamRecorder(endpoint, STREAMS, lambda s: (s.topic, s.seq))


class Bridge:
    """`ftsensord bridge STREAMS --port 0` on a running daemon, with the Python reference
    subscribed before the bridge starts (so it has every sample the bridge serves)."""

    def __init__(self, folder: Path):
        pub = f"ipc://{folder / 'wrench'}"
        self.frames = ControlClient(f"ipc://{folder / 'control'}").status()["frames"]
        self.ref = Reference(pub)
        self.ref.start()
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "ftsensord", "bridge", *STREAMS, "--port", "0", "--endpoint", pub],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        self.err = ""
        line = self.proc.stdout.readline() if self.proc.stdout else ""
        if "ws://127.0.0.1:" not in line:
            self.stop()
            pytest.fail(f"the bridge did not start: {line!r} {self.err}")
        self.url = "ws://127.0.0.1:" + line.split("ws://127.0.0.1:")[1].split()[0]

    def stop(self) -> int:
        """SIGINT, as Ctrl-C; the bridge's exit code (its stderr in ``err``)."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
        _, self.err = self.proc.communicate(timeout=20)
        self.ref.stop.set()
        self.ref.join()
        return self.proc.returncode


@pytest.fixture
def bridge(tmp_path) -> Iterator[Bridge]:
    proc, notify = start_daemon(
        write_config(tmp_path), tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    try:
        b = Bridge(tmp_path / "ftsensord")
        try:
            yield b
        finally:
            b.stop()
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=20)
        notify.close()


def run_client(check_mjs: list[str], *args: str) -> subprocess.CompletedProcess:
    # 60 s: above check.mjs's own --timeout (at most 30 s here), so it reports, not this
    return subprocess.run([*check_mjs, *args], capture_output=True, text=True, timeout=60)


def test_the_foxglove_apps_client_reads_the_streams_as_ros2_messages_at_the_samples_time(check_mjs, bridge):
    # 30 s: node's start and the first samples, with room for a loaded machine
    done = run_client(check_mjs, bridge.url, "--count", str(COUNT), "--timeout", "30", *SCHEMAS)
    assert bridge.stop() == 0 and "Traceback" not in bridge.err and "(stopped by SIGINT)" in bridge.err, (
        bridge.err
    )
    assert done.returncode == 0, done.stderr
    lines = [json.loads(line) for line in done.stdout.splitlines()]
    hello, messages = lines[0], [m for m in lines if "topic" in m]
    assert hello["subprotocol"] == "foxglove.sdk.v1" and hello["serverInfo"]["name"] == "ftsensord"
    channels = {c["topic"]: c for m in lines if "advertised" in m for c in m["advertised"]}
    for topic, schema in SCHEMAS.items():
        assert (channels[topic]["schemaName"], channels[topic]["encoding"]) == (schema, "cdr"), topic
    assert len(messages) == COUNT and {m["topic"] for m in messages} == set(SCHEMAS)

    # Each wrench and its status are one sample's: pair them by log time, seq from the status.
    status = {
        (m["topic"].removesuffix("/status"), m["log_time_ns"]): m for m in messages if m["schema"] == STATUS
    }
    wrenches = [m for m in messages if m["schema"] == WRENCH]
    checked = 0
    for m in wrenches:
        assert m["topic"] in SCHEMAS and m["schema"] == SCHEMAS[m["topic"]]
        st = status.get((m["topic"], m["log_time_ns"]))
        if st is None:
            continue  # subscribed to the wrench, not yet to its status; or after the client's count
        stream, seq = m["topic"][1:], int(st["message"]["seq"])
        sample = bridge.ref.samples[(stream, seq)]
        msg = m["message"]
        sec, nanosec = stamp(sample.t_wall)
        assert (msg["header"]["stamp"]["sec"], msg["header"]["stamp"]["nanosec"]) == (sec, nanosec)
        assert int(m["log_time_ns"]) == sec * 10**9 + nanosec  # the sample's own time, not the arrival's
        assert st["message"]["header"] == msg["header"]
        assert msg["header"]["frame_id"] == bridge.frames[stream]
        assert st["message"]["flags"] == sample.flags
        w = msg["wrench"]
        got = [float(w[part][axis]) for part in ("force", "torque") for axis in "xyz"]  # float(): "NaN" too
        # float64 on the wire, in the CDR and in JSON (shortest round-trip digits): exactly equal
        np.testing.assert_array_equal(got, sample.values)
        checked += 1
    # A stream's first wrench may come before the client's subscription to its status took
    # effect, its last after the client had COUNT messages: two per stream without a status.
    assert checked >= len(wrenches) - 2 * len(STREAMS) and checked >= COUNT // 2 - 2 * len(STREAMS)

    # Every sample served, and `missed` says how many sequence numbers a status skipped.
    for stream in STREAMS:
        seqs = [
            (int(m["message"]["seq"]), m["message"]["missed"])
            for m in messages
            if m["topic"] == f"/{stream}/status"
        ]
        for (prev, _), (seq, missed) in zip(seqs, seqs[1:]):
            assert missed == seq - prev - 1


def test_a_client_offering_only_the_old_subprotocol_is_refused_with_a_clear_error(check_mjs, bridge):
    # foxglove-sdk's server speaks foxglove.sdk.v1 only; a viewer offering just the protocol's
    # old name (older Foxglove app releases, the Lichtblick fork until late 2025) gets HTTP 400:
    # docs/guide/clients.md, Bridges to live viewers.
    done = run_client(
        check_mjs, bridge.url, "--subprotocol", "foxglove.websocket.v1", "--timeout", "10", "/wrench/tip"
    )
    assert done.returncode == 1 and done.stdout == ""
    assert "400" in done.stderr and "foxglove.websocket.v1" in done.stderr, done.stderr
    # The bridge's own log says why (the SDK's server says only "handshake failed").
    bridge.stop()
    assert "handshake failed: a viewer must offer the WebSocket subprotocol foxglove.sdk.v1" in bridge.err, (
        bridge.err
    )
