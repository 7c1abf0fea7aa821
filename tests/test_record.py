"""`ftsensord record` keeps what it received (each format, each way of stopping it),
in flat memory; MCAP read back with mcap's reader and ROS 2 decoding; `echo`
ends cleanly on Ctrl-C and on a closed pipe."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import textwrap
import threading
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from ftsensord import recording
from ftsensord.client import ControlClient, Subscriber
from ftsensord.errors import ConfigError
from ftsensord.protocol import wire
from ftsensord.recording import (
    Tally,
    finish_npz,
    load_rows,
    open_writer,
    read_mcap,
    record,
    recover_mcap,
)
from ftsensord.recording.ros2mcap import stamp

from .test_daemon import write_config

STREAMS = ["wrench/sensor1", "wrench/tip"]
#: sensor1's weight taken off at a fixed mount: its compensated stream, whose sigma is then the raw one's.
GRAVITY = """
[gravity]
orientation = "mount"
[gravity.sensor1]
mass_kg = 0.05
com_m = [0.0, 0.0, 0.01]
mount_rotvec_deg = [0.0, 0.0, 0.0]
"""
COMPENSATED = "wrench/sensor1/compensated"
#: A kill -9 may lose what waited for its flush (0.5 s) and the hop to the recorder: 1 s promised.
KILL_LOSS_S = 1.0
#: A sample published this long before a stop signal has surely reached the recorder's queue.
DELIVERED_S = 0.3

from .conftest import start_daemon


@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    """`ftsensord run` on the simulated bus (sensor1 loaded, static), shared by this module's tests."""
    tmp = tmp_path_factory.mktemp("daemon")
    config = write_config(tmp, extra=GRAVITY)
    proc, notify = start_daemon(config, tmp, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        yield f"ipc://{tmp / 'ftsensord' / 'wrench'}", f"ipc://{tmp / 'ftsensord' / 'control'}"
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
        notify.close()


class Reference(threading.Thread):
    """A Python subscriber receiving in parallel: every sample, by stream and seq."""

    def __init__(self, endpoint: str, streams: list[str]):
        super().__init__(daemon=True)
        self.sub = Subscriber(endpoint, streams)
        self.samples: dict[str, dict[int, wire.Sample]] = {s: {} for s in streams}
        self.done = threading.Event()

    def run(self) -> None:
        while not self.done.is_set():
            s = self.sub.receive(timeout_s=0.1)
            if s is not None:
                self.samples[s.topic][s.seq] = s
        self.sub.close()

    def wait_for(self, n: int) -> None:
        deadline = time.monotonic() + 10
        while min(len(v) for v in self.samples.values()) < n:
            assert time.monotonic() < deadline, "the reference subscriber received nothing"
            time.sleep(0.05)

    def stop(self) -> None:
        self.done.set()
        self.join(timeout=5)


def cli(*args: str, **kw) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "ftsensord", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        **kw,
    )


def seqs_in(path: Path, killed: bool) -> dict[str, list[int]]:
    """Each stream's sequence numbers as the file holds them (after a kill: as the
    documented loaders read what is left)."""
    if path.suffix == ".csv":
        text = path.read_text()
        lines = text.splitlines(keepends=True)
        if killed and lines and not lines[-1].endswith("\n"):
            lines.pop()  # a row torn by the kill
        return {STREAMS[0]: [int(line.split(",")[0]) for line in lines[1:]]}
    if path.suffix == ".npz":
        part = Path(f"{path}.part")
        if killed:
            assert part.exists() and not path.exists()
            rows = load_rows(part)["seq"].tolist()
            assert finish_npz(part) == len(rows) and not part.exists()
        else:
            assert not part.exists()
        return {STREAMS[0]: np.load(path)["seq"].tolist()}
    out: dict[str, list[int]] = {s: [] for s in STREAMS}
    for topic, msg, _ in read_mcap(path):
        if topic.endswith("/status"):
            out[topic[1 : -len("/status")]].append(msg.seq)
    return out


def check_kept(path: Path, ref: Reference, streams: list[str], t_stop: float, killed: bool) -> dict[str, int]:
    """No received sample lost: the file's seqs are the reference's, without a hole,
    up to the stop (after a kill: up to the stop less KILL_LOSS_S). Returns the counts."""
    got = seqs_in(path, killed)
    counts = {}
    for stream in streams:
        seqs, seen = got[stream], ref.samples[stream]
        assert seqs and seqs == sorted(seqs), stream
        assert set(seqs) <= set(seen), f"{stream}: seqs the reference never saw"
        expected = [q for q in sorted(seen) if seqs[0] <= q <= seqs[-1]]
        assert seqs == expected, f"{stream}: {len(set(expected) - set(seqs))} samples missing"
        margin = KILL_LOSS_S if killed else DELIVERED_S
        before = [q for q, s in seen.items() if s.t_mono <= t_stop - margin]
        assert seqs[-1] >= max(before), f"{stream}: stopped {seqs[-1]}, reference had {max(before)}"
        counts[stream] = len(seqs)
    return counts


@pytest.mark.parametrize("fmt", ["csv", "npz", "mcap"])
@pytest.mark.parametrize(
    "how",
    [signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGKILL],
    ids=["SIGINT", "SIGTERM", "SIGHUP", "kill-9"],
)
def test_record_stopped_keeps_every_received_sample(daemon, tmp_path, fmt, how):
    pub, _ = daemon
    streams = STREAMS if fmt == "mcap" else STREAMS[:1]
    path = tmp_path / f"rec.{fmt}"
    ref = Reference(pub, streams)
    ref.start()
    try:
        ref.wait_for(5)
        proc = cli("record", *streams, str(path), "--endpoint", pub)
        time.sleep(2.0)
        t_stop = time.monotonic()
        proc.send_signal(how)
        out, err = proc.communicate(timeout=20)
        time.sleep(0.3)
    finally:
        ref.stop()
    killed = how == signal.SIGKILL
    assert proc.returncode == (-signal.SIGKILL if killed else 0), err
    assert "Traceback" not in err
    counts = check_kept(path, ref, streams, t_stop, killed)
    if not killed:  # a clean end: the summary is the file's
        assert f"(stopped by {signal.Signals(how).name})" in out
        for stream, n in counts.items():
            assert f"{stream}: {n} samples, " in out
        if fmt == "csv":  # the sidecar has the count
            meta = recording.read_meta(path)
            frame = ControlClient(daemon[1]).status()["frames"][STREAMS[0]]
            assert (meta["stream"], meta["frame"], meta["state"]) == (STREAMS[0], frame, "complete")
            assert meta["samples"] == meta["received"] == counts[STREAMS[0]]
        if fmt == "mcap":  # complete: summary and index, read by the seeking reader
            from mcap.reader import make_reader

            with open(path, "rb") as f:
                summary = make_reader(f).get_summary()
            assert summary is not None and summary.chunk_indexes
            # a wrench, its sigma and its status a sample
            assert summary.statistics.message_count == 3 * sum(counts.values())
    elif fmt == "csv":  # the sidecar as the kill left it: the rows are counted in the CSV
        meta = recording.read_meta(path)
        assert meta["state"] == "recording" and meta["samples"] == counts[STREAMS[0]]
    elif fmt == "mcap":  # cut short, yet recoverable into a complete file
        fixed = tmp_path / "fixed.mcap"
        assert recover_mcap(path, fixed) == 3 * sum(counts.values())  # a wrench, its sigma, its status
        from mcap.reader import make_reader

        with open(fixed, "rb") as f:
            assert make_reader(f).get_summary().statistics.message_count == 3 * sum(counts.values())


class Synthetic:
    """A receiver of n made-up samples, one per call (no sockets: memory is the recorder's)."""

    def __init__(self, n: int, stream: str, values: int):
        self.n, self.i, self.stream, self.values = n, 0, stream, values

    def receive(self, timeout_s: float | None = None) -> wire.Sample | None:
        if self.i >= self.n:
            return None
        self.i += 1
        kind = wire.KIND_WRENCH if self.stream.startswith("wrench/") else wire.KIND_FLUX
        return wire.Sample(
            self.stream,
            kind,
            self.i,
            self.i * 0.01,
            1.7e9 + self.i * 0.01,
            0,
            np.full(self.values, self.i * 1e-3),
        )


@pytest.mark.parametrize("fmt", ["csv", "npz", "mcap"])
def test_record_memory_stays_flat(tmp_path, fmt):
    """Ten times the samples, not ten times the memory: the writers keep at most a
    flush's worth (the old recorder kept every row, ~0.4 kB each on a flux stream)."""
    peaks = []
    for n in (1_000, 10_000):
        ticks = iter(range(10**9))

        def clock(ticks=ticks) -> float:  # 1 ms per look: a flush every ~100 samples
            return next(ticks) * 1e-3

        writer = open_writer(tmp_path / f"m{n}.{fmt}", ["wrench/sensor1"])
        source = Synthetic(n, "wrench/sensor1", 6)
        tracemalloc.start()
        outcome = record(
            source,
            writer,
            ["wrench/sensor1"],
            timeout_s=1e9,
            clock=clock,
            stop=lambda source=source: source.i >= source.n,
        )
        peaks.append(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
        assert outcome.reason == "stopped" and outcome.tallies["wrench/sensor1"].samples == n
    # 9,000 more rows kept as the old recorder kept them (a tuple of 10 floats) would be > 3 MB;
    # MCAP's chunk index grows ~0.1 kB a flush (90 more here).
    assert peaks[1] - peaks[0] < 300_000, peaks


def test_mcap_holds_ros2_messages_matching_what_was_published(daemon, tmp_path):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    pub, ctl = daemon
    streams = [*STREAMS, COMPENSATED, "flux/sensor1"]
    path = tmp_path / "rec.mcap"
    ref = Reference(pub, streams)
    ref.start()
    try:
        ref.wait_for(5)
        done = subprocess.run(
            [
                sys.executable,
                "-m",
                "ftsensord",
                "record",
                *streams,
                str(path),
                "--endpoint",
                pub,
                "--count",
                "150",
            ],
            capture_output=True,
            text=True,
            timeout=60,
        )
        time.sleep(0.3)
    finally:
        ref.stop()
    assert done.returncode == 0, done.stderr
    frames = ControlClient(ctl).status()["frames"]
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        types = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
        assert types["/wrench/sensor1"] == types["/wrench/tip"] == "geometry_msgs/msg/WrenchStamped"
        assert types["/flux/sensor1/chip7"] == "sensor_msgs/msg/MagneticField"
        assert types["/wrench/sensor1/sigma"] == "geometry_msgs/msg/WrenchStamped"
        assert set(types) == {
            "/wrench/sensor1",
            "/wrench/tip",
            "/wrench/sensor1/sigma",
            "/wrench/tip/sigma",
            "/wrench/sensor1/status",
            "/wrench/tip/status",
            f"/{COMPENSATED}",
            f"/{COMPENSATED}/sigma",
            f"/{COMPENSATED}/status",
            "/flux/sensor1/status",
            *(f"/flux/sensor1/chip{i}" for i in range(8)),
        }
        checked = dict.fromkeys(types, 0)
        pending: dict[str, list] = {}
        for _, channel, message, msg in reader.iter_decoded_messages(log_time_order=False):
            topic = channel.topic
            checked[topic] += 1
            if topic.endswith("/status"):
                sample = ref.samples[topic[1 : -len("/status")]][msg.seq]
                assert msg.flags == sample.flags and message.sequence == msg.seq & 0xFFFFFFFF
                for other in pending.pop(topic[1 : -len("/status")], []):  # the values before it: same sample
                    other(sample)
            else:
                stream = topic[1:] if topic.startswith("/wrench/") else topic[1:].rsplit("/", 1)[0]
                stream = stream.removesuffix("/sigma")
                pending.setdefault(stream, []).append(
                    lambda s, m=msg, t=topic, lt=message.log_time: _matches(s, m, t, lt, frames)
                )
    assert not any(pending.values())
    assert all(n > 0 for n in checked.values()), checked
    assert sum(checked[f"/{s}/status"] for s in streams) >= 150


def _matches(sample: wire.Sample, msg, topic: str, log_time: int, frames: dict[str, str]) -> None:
    sec, nanosec = stamp(sample.t_wall)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (sec, nanosec)
    assert abs(sec + nanosec * 1e-9 - sample.t_wall) < 1e-6 and log_time == sec * 10**9 + nanosec
    if topic.startswith("/wrench/"):
        assert msg.header.frame_id == frames[topic[1:].removesuffix("/sigma")]
        w = msg.wrench
        got = [w.force.x, w.force.y, w.force.z, w.torque.x, w.torque.y, w.torque.z]
        if topic.endswith("/sigma"):  # the sample's sigma, the daemon's companion
            assert sample.sigma is not None
            np.testing.assert_array_equal(got, sample.sigma)  # float64 both ways: exact, NaN where unknown
            assert np.all(np.isfinite(got))  # at rest, every sample's is known (at a mount, compensated too)
        else:
            assert got == sample.values.tolist()  # float64 both ways: exact
    else:
        chip = int(topic.rsplit("chip", 1)[1])
        b = msg.magnetic_field
        np.testing.assert_array_equal([b.x, b.y, b.z], sample.values[3 * chip : 3 * chip + 3])
        assert msg.header.frame_id == f"sensor1/chip{chip}"


@pytest.mark.parametrize("stream", ["wrench/sensor1", COMPENSATED, "flux/sensor1"])
def test_a_csv_recording_reads_with_the_usual_readers_and_its_sidecar_says_what_it_is(
    daemon, tmp_path, stream
):
    """A recording from the daemon read as docs/guide/clients.md says, each reader with its
    defaults (numpy: the delimiter, as its default is whitespace): every row, each number
    the published sample's (to the CSV's digits: 9 significant, times to the us); the
    sidecar names the stream, frame, columns, units and flag bits and counts the rows."""
    import csv

    import pandas

    pub, ctl = daemon
    path = tmp_path / "run.csv"
    ref = Reference(pub, [stream])
    ref.start()
    try:
        ref.wait_for(5)
        done = subprocess.run(
            [
                sys.executable,
                "-m",
                "ftsensord",
                "record",
                stream,
                str(path),
                "--endpoint",
                pub,
                "--count",
                "40",
            ],
            capture_output=True,
            text=True,
            timeout=60,
        )
        time.sleep(0.3)
    finally:
        ref.stop()
    assert done.returncode == 0, done.stderr
    names = (
        ["fx_N", "fy_N", "fz_N", "mx_Nm", "my_Nm", "mz_Nm"]
        if stream.startswith("wrench/")
        else [f"b{i}{a}_T" for i in range(8) for a in "xyz"]
    )
    sigmas = ["sigma_" + n for n in names] if stream.startswith("wrench/") else []  # each axis's sigma
    columns = ["seq", "t_mono_s", "t_wall_s", "flags", *names, *sigmas]

    def check(table: list[list[float]]) -> None:  # rows of the columns above, as a reader gave them
        assert len(table) == 40
        for row in table:
            sample = ref.samples[stream][int(row[0])]
            assert row[0] == sample.seq and row[3] == sample.flags
            assert row[1] == pytest.approx(sample.t_mono, abs=1e-6) and row[2] == pytest.approx(
                sample.t_wall, abs=1e-6
            )
            np.testing.assert_allclose(row[4 : 4 + len(names)], sample.values, rtol=1e-8, atol=0)
            if sigmas:  # 9 significant digits, NaN where the daemon does not know it
                assert sample.sigma is not None and np.all(np.isfinite(sample.sigma))
                np.testing.assert_allclose(row[4 + len(names) :], sample.sigma, rtol=1e-8, atol=0)

    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        assert reader.fieldnames == columns
        check([[float(r[c]) for c in columns] for r in reader])
    table = np.genfromtxt(path, delimiter=",", names=True)
    assert list(table.dtype.names) == columns
    check([list(r) for r in table.tolist()])
    frame = pandas.read_csv(path)
    assert list(frame.columns) == columns and frame["seq"].dtype.kind == "i"
    check(frame.to_numpy().tolist())

    # docs/guide/clients.md's snippet as written, in the recording's folder: the same rows.
    doc = (Path(__file__).parent.parent / "docs" / "guide" / "clients.md").read_text()
    snippet = re.search(r"```python\n( *import csv, numpy, pandas\n.*?) *```", doc, re.DOTALL).group(1)
    names_in_doc = {}
    cwd = Path.cwd()
    try:
        os.chdir(tmp_path)
        exec(textwrap.dedent(snippet).replace('"fz_N"', f'"{names[2]}"'), names_in_doc)
    finally:
        os.chdir(cwd)
    check([[float(r[c]) for c in columns] for r in names_in_doc["rows"]])
    check([list(r) for r in names_in_doc["table"].tolist()])
    check(names_in_doc["frame"].to_numpy().tolist())

    meta = recording.read_meta(path)
    seqs = [int(r[0]) for r in table.tolist()]
    assert meta["stream"] == stream and meta["frame"] == ControlClient(ctl).status()["frames"][stream]
    assert meta["kind"] == stream.split("/")[0] and meta["columns"] == columns
    assert {c: meta["units"][c] for c in names} == {c: c.rsplit("_", 1)[1] for c in names}
    for c in sigmas:  # its unit, what it is, and what an empty or nan cell means
        unit = meta["units"][c]
        assert unit.startswith(c.rsplit("_", 1)[1] + ", the daemon's 1-sigma of " + c.removeprefix("sigma_"))
        assert "empty: not received" in unit
    assert meta["units"]["t_mono_s"].startswith("s, CLOCK_MONOTONIC") and meta["units"][
        "t_wall_s"
    ].startswith("s, Unix")
    assert meta["flag_bits"] == {name: bit for bit, name in wire.FLAG_NAMES.items()}
    assert (meta["state"], meta["samples"], meta["received"], meta["error"]) == ("complete", 40, 40, None)
    assert (meta["first_seq"], meta["last_seq"]) == (seqs[0], seqs[-1])
    assert meta["missed"] == seqs[-1] - seqs[0] + 1 - 40


def test_a_csv_sidecar_that_is_missing_or_not_ours_is_refused_naming_it(tmp_path):
    path = tmp_path / "run.csv"
    path.write_text("seq,t_mono_s\n1,2.0\n")
    with pytest.raises(
        ConfigError, match=r"run\.csv\.json: missing: `ftsensord record` writes it beside run\.csv"
    ):
        recording.read_meta(path)
    (tmp_path / "run.csv.json").write_text("# not json")
    with pytest.raises(ConfigError, match=r"run\.csv\.json: not JSON: expected the sidecar"):
        recording.read_meta(path)
    (tmp_path / "run.csv.json").write_text("{}")
    with pytest.raises(ConfigError, match=r"run\.csv\.json: not an ftsensord CSV sidecar"):
        recording.read_meta(path)


def test_csv_and_npz_refuse_several_streams(tmp_path):
    with pytest.raises(ValueError, match="holds one stream"):
        open_writer(tmp_path / "x.csv", STREAMS)
    with pytest.raises(ValueError, match=r"\.csv, \.npz or \.mcap"):
        open_writer(tmp_path / "x.txt", STREAMS[:1])


def test_npz_sidecar_killed_before_and_after_its_first_sample(tmp_path):
    """Killed (never closed, never flushed) before the first sample: the sidecar says that
    nothing was recorded; after it: the header and that sample read back."""
    writer = open_writer(tmp_path / "x.npz", STREAMS[:1])
    part = tmp_path / "x.npz.part"
    with pytest.raises(ConfigError, match="x.npz.part: empty: the recording ended before its first sample"):
        load_rows(part)
    writer.write(wire.Sample(STREAMS[0], wire.KIND_WRENCH, 7, 1.0, 1.7e9, 0, np.arange(6.0)))
    rows = load_rows(part)
    assert rows["seq"].tolist() == [7] and rows["values"].tolist() == [list(np.arange(6.0))]
    assert rows["stream"] == STREAMS[0]


@pytest.mark.parametrize("stream", ["wrench/sensor1", COMPENSATED, "flux/sensor1"])
def test_echo_prints_a_header_naming_each_column_and_its_unit_over_it(daemon, stream):
    pub, _ = daemon
    done = subprocess.run(
        [sys.executable, "-m", "ftsensord", "echo", stream, "--endpoint", pub, "--count", "3"],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert done.returncode == 0, done.stderr
    head, *rows = done.stdout.splitlines()
    wrench = ["fx_N", "fy_N", "fz_N", "mx_Nm", "my_Nm", "mz_Nm"]
    values = (
        wrench + ["s_" + n for n in wrench]  # and each axis's sigma
        if stream.startswith("wrench/")
        else [f"b{i}{a}_uT" for i in range(8) for a in "xyz"]
    )  # flux is printed in uT
    assert head.startswith("#") and head[1:].split() == ["seq", "t_mono_s", *values, "flags"], head
    assert len(rows) == 3
    if stream.startswith(
        "wrench/"
    ):  # each sample's sigma came with it: known at rest (at a mount, compensated too)
        assert all(np.all(np.isfinite([float(v) for v in row.split()[8:14]])) for row in rows), rows
    n = 2 + len(values)  # seq, t_mono_s and the values; then the flags' names, if any
    name_ends = [m.end() for m in re.finditer(r"\S+", " " + head[1:])][:n]
    for row in rows:  # each name ends where its numbers end
        assert [m.end() for m in re.finditer(r"\S+", row)][:n] == name_ends, (head, row)
        assert len([float(v) for v in row.split()[:n]]) == n  # numbers (NaN: a chip that did not answer)


@pytest.mark.parametrize("command", ["echo", "record", "plot"])
def test_a_stream_the_daemon_does_not_publish_is_refused_naming_those_it_does(daemon, tmp_path, command):
    pub, ctl = daemon
    published = ControlClient(ctl).status()["streams"]
    assert "wrench/sensor1" in published and "flux/sensor1" in published
    extra = {"echo": [], "record": [str(tmp_path / "x.csv")], "plot": ["--png", str(tmp_path / "x.png")]}[
        command
    ]
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "ftsensord",
            command,
            "wrench/sensr1",
            *extra,
            "--endpoint",
            pub,
            "--timeout",
            "2",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip() == (
        f"ftsensord: wrench/sensr1: not a stream the daemon on {ctl} publishes; "
        f"it publishes: {', '.join(published)}"
    ), done.stderr


def test_echo_into_a_closed_pipe_exits_quietly(daemon):
    pub, _ = daemon
    proc = cli("echo", "wrench/sensor1", "--endpoint", pub)
    assert proc.stdout.readline() and proc.stdout.readline()
    proc.stdout.close()  # as `| head -2` does
    err = proc.stderr.read()
    assert proc.wait(timeout=10) == 0 and "Traceback" not in err and "Broken pipe" not in err, err


def test_ctrl_c_ends_echo_and_other_commands_without_a_traceback(daemon, tmp_path):
    pub, _ = daemon
    proc = cli("echo", "wrench/sensor1", "--endpoint", pub)
    assert proc.stdout.readline()
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=10)
    assert proc.returncode == 0 and "Traceback" not in err and " samples" in err, err
    # A command waiting on a daemon that never answers: Ctrl-C gives 130 and a line.
    proc = cli("status", "--control", f"ipc://{tmp_path}/nobody", "--timeout", "30")
    time.sleep(1.5)  # into the wait
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=10)
    assert proc.returncode == 130 and err.strip() == "ftsensord: interrupted", err


DISK_FULL = """
import resource, signal
import numpy as np
from ftsensord.recording import CsvWriter, record
from ftsensord.protocol import wire

class Synthetic:  # tests/test_record.py's, without the test modules' imports
    i = 0
    def receive(self, timeout_s=None):
        self.i += 1
        return None if self.i > 2000 else wire.Sample("wrench/sensor1", wire.KIND_WRENCH, self.i, self.i * 0.01,
                                                      1.7e9, 0, np.full(6, self.i * 1e-3))

signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # past the limit write() fails (EFBIG), as on a full disk
resource.setrlimit(resource.RLIMIT_FSIZE, (50_000, 50_000))
try:
    record(Synthetic(), CsvWriter({path!r}, "wrench/sensor1"), ["wrench/sensor1"])
except OSError as exc:
    print("error", exc.errno)
"""


def test_a_csv_record_cut_by_a_write_error_says_how_many_samples_it_holds(tmp_path):
    """The disk fills (here: the file size limit, the same failed write) after a few hundred
    of 2000 samples: the sidecar counts the rows in the file, not the samples received; the
    row the error tore is cut off the CSV (every reader reads the rest) and kept in the
    sidecar; the error still reaches the caller."""
    import csv

    path = tmp_path / "r.csv"
    code = DISK_FULL.format(path=str(path))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.stdout.startswith("error"), out.stdout + out.stderr
    text = path.read_bytes().decode("ascii")
    assert text.endswith("\n")  # no torn row left
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert 0 < len(rows) < 2000 and [int(r["seq"]) for r in rows] == list(range(1, len(rows) + 1))
    meta = recording.read_meta(path)
    assert meta["state"] == "write error" and meta["samples"] == len(rows), meta
    assert meta["received"] >= len(rows) and meta["error"] == "File too large"
    n = len(rows) + 1  # the torn row's sample: DISK_FULL's values
    full = f"{n},{n * 0.01:.6f},{1.7e9:.6f},0," + ",".join([f"{n * 1e-3:.9g}"] * 6) + "\n"
    assert meta["torn_row"] and full.startswith(meta["torn_row"]) and meta["torn_row"] != full, meta[
        "torn_row"
    ]


DISK_FULL_ANY = """
import resource, signal
import numpy as np
from ftsensord.recording import open_writer, record
from ftsensord.protocol import wire

class Synthetic:
    i = 0
    def receive(self, timeout_s=None):
        self.i += 1
        return None if self.i > 5000 else wire.Sample("wrench/sensor1", wire.KIND_WRENCH, self.i, self.i * 0.01,
                                                      1.7e9, 0, np.full(6, self.i * 1e-3))

signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (50_000, 50_000))
try:
    record(Synthetic(), open_writer({path!r}, ["wrench/sensor1"]), ["wrench/sensor1"], flush_every_s=0)
except OSError as exc:
    print("error", exc.errno, exc.filename)
    print(exc)
"""


@pytest.mark.parametrize("fmt", ["csv", "npz", "mcap"])
def test_a_write_error_names_the_file_it_could_not_write(tmp_path, fmt):
    """A full disk (the file size limit: the same failed write) ends `record` with an
    OSError that names the file, so `ftsensord record`'s message ("ftsensord: [Errno 27]
    File too large: '.../run.csv'") says which file: a bare write() error names none."""
    path = tmp_path / f"r.{fmt}"
    out = subprocess.run(
        [sys.executable, "-c", DISK_FULL_ANY.format(path=str(path))],
        capture_output=True,
        text=True,
        timeout=60,
    )
    first, message = (out.stdout.splitlines() + ["", ""])[:2]
    assert first.startswith("error 27 "), out.stdout + out.stderr  # EFBIG
    named = path if fmt != "npz" else tmp_path / "r.npz.part"  # the NPZ's rows go to its sidecar first
    assert first == f"error 27 {named}" and str(named) in message, out.stdout


@pytest.mark.parametrize("fmt", ["csv", "npz", "mcap"])
def test_the_temperature_flag_reaches_every_recording(tmp_path, fmt):
    """Bit 11 (`temperature`) as any other flag: the CSV's and NPZ's flags column and the
    MCAP status message's flags carry it."""
    path = tmp_path / f"x.{fmt}"
    writer = open_writer(path, STREAMS[:1])
    flags = wire.FLAG_TEMPERATURE | wire.FLAG_INCONSISTENT
    writer.write(wire.Sample(STREAMS[0], wire.KIND_WRENCH, 3, 1.0, 1.7e9, flags, np.arange(6.0)))
    tally = Tally()
    tally.add(3)
    writer.close({STREAMS[0]: tally})
    if fmt == "csv":
        row = [line for line in path.read_text().splitlines() if line.startswith("3,")][0]
        assert int(row.split(",")[3]) == flags
    elif fmt == "npz":
        assert np.load(path)["flags"].tolist() == [flags]
    else:
        status = [m for topic, m, _ in read_mcap(path) if topic.endswith("/status")]
        assert [m.flags for m in status] == [flags]
    assert wire.flag_names(flags) == ["inconsistent", "temperature"]


@pytest.mark.parametrize("fmt", ["csv", "npz", "mcap"])
def test_each_wrench_is_recorded_with_its_sigma_and_unknown_when_none_came(tmp_path, fmt):
    """A wrench's sigma beside it in every format: the CSV's six `sigma_*` columns, the NPZ's
    `sigma`, the MCAP's `<topic>/sigma`; a sample whose companion never came is unknown (an
    empty CSV cell, NaN), and the daemon's own NaN (an unknown axis) stays NaN."""
    path = tmp_path / f"x.{fmt}"
    writer = open_writer(path, STREAMS[:1])
    sigma = np.array([0.025, 0.031, 0.022, 0.003, 0.0029, np.nan])
    sent = [
        wire.Sample(STREAMS[0], wire.KIND_WRENCH, 3, 1.0, 1.7e9, 0, np.arange(6.0), sigma),
        wire.Sample(STREAMS[0], wire.KIND_WRENCH, 4, 1.01, 1.7e9 + 0.01, 0, np.arange(6.0)),  # none came
    ]
    tally = Tally()
    for s in sent:
        writer.write(s)
        tally.add(s.seq)
    writer.close({STREAMS[0]: tally})
    nan6 = np.full(6, np.nan)
    if fmt == "csv":
        lines = path.read_text().splitlines()
        assert lines[0].split(",")[-6:] == [
            "sigma_fx_N",
            "sigma_fy_N",
            "sigma_fz_N",
            "sigma_mx_Nm",
            "sigma_my_Nm",
            "sigma_mz_Nm",
        ]
        assert lines[1].split(",")[-6:] == ["0.025", "0.031", "0.022", "0.003", "0.0029", "nan"]
        assert lines[2].split(",")[-6:] == [""] * 6  # not received
        got = np.genfromtxt(path, delimiter=",", names=True)
        np.testing.assert_array_equal([list(r)[-6:] for r in got.tolist()], [sigma, nan6])
    elif fmt == "npz":
        np.testing.assert_array_equal(np.load(path)["sigma"], [sigma, nan6])
    else:
        got = [m.wrench for topic, m, _ in read_mcap(path) if topic == f"/{STREAMS[0]}/sigma"]
        vectors = [[w.force.x, w.force.y, w.force.z, w.torque.x, w.torque.y, w.torque.z] for w in got]
        np.testing.assert_array_equal(vectors, [sigma, nan6])


@pytest.mark.parametrize(
    "args",
    [
        ("status", "--control", "nonsense"),
        ("status", "--control", "tcp://127.0.0.1:*"),
        ("echo", "wrench/sensor1", "--endpoint", "ipc://", "--timeout", "0.2"),
        ("record", "wrench/sensor1", "{tmp}/x.csv", "--endpoint", "tcp://127.0.0.1:", "--timeout", "0.2"),
    ],
)
def test_an_endpoint_zeromq_cannot_connect_to_is_a_message_not_a_traceback(tmp_path, args):
    """`--control nonsense` ended every command with a ZMQError traceback ("Invalid argument")."""
    args = tuple(a.format(tmp=tmp_path) for a in args)
    proc = cli(*args)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 2 and "Traceback" not in err, err
    endpoint = (
        args[args.index("--control") + 1] if "--control" in args else args[args.index("--endpoint") + 1]
    )
    last = err.strip().splitlines()[-1]  # (record first says no daemon answered for the frames)
    assert last.startswith(f"ftsensord: {endpoint}: ") and "ipc://PATH or tcp://HOST:PORT" in last, err
    assert not (tmp_path / "x.csv").exists()  # record refused it before making its file


def test_the_client_classes_refuse_an_endpoint_zeromq_cannot_connect_to(zmq_context):
    from ftsensord.client import OrientationPublisher

    for make in (
        lambda: ControlClient("nonsense", context=zmq_context).status(),
        lambda: Subscriber("tcp://127.0.0.1:", ["wrench/sensor1"], context=zmq_context),
        lambda: OrientationPublisher("ipc://", context=zmq_context),
    ):
        with pytest.raises(ConfigError, match="ipc://PATH or tcp://HOST:PORT"):
            make()


@pytest.mark.parametrize("reply", [b"garbage", b"[1, 2]", b'"ok"', b"\xff\xfe", b"[" * 10_000])
def test_a_control_reply_that_is_not_a_json_object_is_a_control_error(zmq_context, reply):
    """Another program on the control endpoint (or a corrupted reply): `ControlClient` raised
    JSONDecodeError or AttributeError ('list' object has no attribute 'get'), which the
    command line printed as a traceback."""
    import zmq

    from ftsensord.errors import ControlError

    router = zmq_context.socket(zmq.ROUTER)
    port = router.bind_to_random_port("tcp://127.0.0.1")

    def answer():
        if router.poll(5000):
            envelope = router.recv_multipart()[:-1]
            router.send_multipart([*envelope, reply])

    t = threading.Thread(target=answer)
    t.start()
    try:
        with pytest.raises(ControlError, match="not a JSON object"):
            ControlClient(f"tcp://127.0.0.1:{port}", timeout_s=5, context=zmq_context).status()
    finally:
        t.join()
        router.close(0)


@pytest.mark.parametrize("stream", ["flux/sensor1", "wrench/sensor1"])
def test_the_npz_sidecar_reads_by_hand_as_docs_clients_md_lays_it_out(tmp_path, stream):
    """An independent reader of a killed NPZ recording's `.npz.part`, from the page alone: a
    JSON line naming `count` and `sigma`, then records of i64 seq, f64 t_mono, f64 t_wall,
    i64 flags, `count` f64 values and, with `sigma` (a wrench stream), 6 f64 sigma,
    little-endian (the layout was not on the page)."""
    import json
    import struct

    writer = open_writer(tmp_path / "r.npz", [stream])
    n = 24 if stream.startswith("flux/") else 6
    sent = [
        wire.Sample(
            stream,
            wire.KIND_FLUX if n == 24 else wire.KIND_WRENCH,
            7 + i,
            0.5 * i,
            1.7e9 + i,
            0x41 * i,
            np.arange(float(n)) * (i + 1) * 1e-6,
            None if n == 24 else np.arange(6.0) * (i + 1) * 1e-3,
        )
        for i in range(3)
    ]
    for s in sent:
        writer.write(s)
    writer.flush()  # as a kill leaves it: no close
    raw = (tmp_path / "r.npz.part").read_bytes()
    line, _, body = raw.partition(b"\n")
    head = json.loads(line)
    count, sigma = head["count"], 6 if head["sigma"] else 0
    assert (count, sigma) == ((24, 0) if n == 24 else (6, 6))
    layout = f"<qddq{count}d{sigma}d"
    size = struct.calcsize(layout)
    assert len(body) == 3 * size
    for i, s in enumerate(sent):
        seq, t_mono, t_wall, flags, *values = struct.unpack_from(layout, body, i * size)
        assert (seq, t_mono, t_wall, flags) == (s.seq, s.t_mono, s.t_wall, s.flags) and values[
            :count
        ] == list(s.values)
        assert values[count:] == ([] if s.sigma is None else list(s.sigma))
    writer.file.close()


def test_a_subscriber_reaches_a_publisher_on_ipv6_loopback(zmq_context, ipv6_loopback):
    """`tcp://[::1]:PORT` is a loopback endpoint the configuration accepts; libzmq connects to
    it only with ZMQ_IPV6 set, so a Subscriber given it waited for ever (2026-11-27)."""
    import zmq

    pub = zmq_context.socket(zmq.PUB)
    pub.setsockopt(zmq.IPV6, 1)
    port = pub.bind_to_random_port("tcp://[::1]")
    sample = wire.Sample("wrench/sensor1", wire.KIND_WRENCH, 5, 1.0, 1.7e9, 0, np.arange(6.0))
    with Subscriber(f"tcp://[::1]:{port}", ["wrench/sensor1"], context=zmq_context) as sub:
        got = None
        for _ in range(50):  # a slow joiner: publish until the subscription has arrived
            pub.send(
                wire.encode(
                    sample.topic,
                    sample.kind,
                    sample.seq,
                    sample.t_mono,
                    sample.t_wall,
                    sample.flags,
                    sample.values,
                )
            )
            got = sub.receive(timeout_s=0.1)
            if got is not None:
                break
    pub.close(0)
    assert got is not None and got.seq == 5 and np.array_equal(got.values, np.arange(6.0))
