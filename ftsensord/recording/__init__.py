"""Recording streams to disk as they arrive: CSV, NPZ (through a sidecar) and MCAP.

Every writer holds at most `FLUSH_EVERY_S` of samples in the process, so memory
stays flat however long a recording runs, and a recorder killed outright
(``kill -9``, a power-less crash of the process, not of the host) loses at most
that much; what was flushed is in the kernel's page cache and reaches the disk
without the process. Ending cleanly (count, time, SIGINT/SIGTERM/SIGHUP) makes
the file complete and returns a per-stream summary.

- **CSV** (one stream): the column names, then a row per sample as it comes, so
  any CSV reader takes it with its defaults; the stream, frame, units and counts
  are in the sidecar ``FILE.csv.json`` (`csvfile`, `read_meta`).
- **NPZ** (one stream): a zip cannot be appended to safely, so rows go to a
  sidecar ``FILE.npz.part`` (a JSON line, then fixed-size binary records) and
  the ``.npz`` is built from it at a clean end, the sidecar then removed. After a
  kill the sidecar stays: `load_rows` reads it (a torn last record is dropped),
  `finish_npz` turns it into the ``.npz``.
- **MCAP** (any number of streams): each wrench a ROS 2 ``geometry_msgs/msg/WrenchStamped``
  (CDR), each chip of a flux stream a ``sensor_msgs/msg/MagneticField``, and per
  stream a companion ``<topic>/status`` (``ftsensord_msgs/msg/SampleStatus``: seq,
  flags, missed). A chunk is closed every `FLUSH_EVERY_S`; the summary and index
  come at a clean end. A file cut short still reads, chunk by chunk, with
  `read_mcap` (mcap's non-seeking reader) and `recover_mcap` rewrites it whole.
"""

from __future__ import annotations

import json
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from ..errors import ConfigError
from ..service import wire
from .columns import WRENCH_COLUMNS, Tally, value_columns  # noqa: F401 (the package's face)
from .csvfile import CsvWriter, read_meta  # noqa: F401
from .ros2mcap import read_mcap, recover_mcap  # noqa: F401

#: Longest a received sample waits in the process before it is handed to the
#: kernel: half the one second a kill may cost, so a slow flush still meets it.
FLUSH_EVERY_S = 0.5


class SampleWriter(Protocol):
    file: Any  # the open file the rows go to (named when writing it fails)

    def write(self, sample: wire.Sample) -> None: ...
    def flush(self) -> None: ...
    def close(self, tallies: dict[str, Tally]) -> None: ...


def _rows_dtype(count: int) -> np.dtype:
    return np.dtype([("seq", "<i8"), ("t_mono", "<f8"), ("t_wall", "<f8"), ("flags", "<i8"),
                     ("values", "<f8", (count,))])


class NpzWriter:
    """One stream to ``.npz``, through the sidecar ``<path>.part`` written as rows come."""

    def __init__(self, path: str | Path, stream: str, frame: str | None = None):
        self.path, self.stream, self.frame = Path(path), stream, frame or stream
        self.part = Path(f"{self.path}.part")
        self.file = open(self.part, "wb")
        self.dtype: np.dtype | None = None

    def write(self, sample: wire.Sample) -> None:
        first = self.dtype is None
        if first:
            self.dtype = _rows_dtype(len(sample.values))
            head = {"format": "ftsensord-rows", "version": 1, "stream": self.stream, "frame": self.frame,
                    "kind": sample.kind,
                    "count": len(sample.values), "columns": value_columns(self.stream, len(sample.values))}
            self.file.write(json.dumps(head).encode() + b"\n")
        row = np.zeros((), self.dtype)
        row["seq"], row["t_mono"], row["t_wall"], row["flags"] = sample.seq, sample.t_mono, sample.t_wall, sample.flags
        row["values"] = sample.values
        self.file.write(row.tobytes())
        if first:  # the header on disk at once: killed before the first flush, the file still reads
            self.file.flush()

    def flush(self) -> None:
        self.file.flush()

    def close(self, tallies: dict[str, Tally]) -> None:
        self.file.close()
        if self.dtype is None:  # nothing received: an empty file of the same keys
            np.savez(self.path, seq=np.zeros(0, np.int64), t_mono=np.zeros(0), t_wall=np.zeros(0),
                     flags=np.zeros(0, np.int64), values=np.zeros((0, 0)), gaps=0, stream=self.stream,
                     frame=self.frame)
            self.part.unlink()
            return
        finish_npz(self.part, self.path)


#: Rows a step of `gaps_of` and `finish_npz` holds in memory (1 MB of a flux stream).
CHUNK_ROWS = 4096


def load_rows(part: str | Path) -> dict[str, Any]:
    """The rows of an NPZ sidecar (``FILE.npz.part``), as the ``.npz`` would hold them.

    Memory-mapped columns, so a long recording is not read into memory; a record
    torn by a kill (the file's length not a whole number of records) is dropped.
    """
    part = Path(part)
    with open(part, "rb") as f:
        line = f.readline()
    if not line:  # the header goes out with the first row (`NpzWriter.write`)
        raise ConfigError(f"{part}: empty: the recording ended before its first sample")
    try:
        head = json.loads(line)
        count = int(head["count"])
    except (ValueError, KeyError, TypeError) as exc:
        raise ConfigError(f"{part}: not an ftsensord rows sidecar (first line: JSON with \"count\")") from exc
    dtype = _rows_dtype(count)
    n = (part.stat().st_size - len(line)) // dtype.itemsize
    rows = (np.memmap(part, dtype=dtype, mode="r", offset=len(line), shape=(n,)) if n
            else np.zeros(0, dtype))
    return {"seq": rows["seq"], "t_mono": rows["t_mono"], "t_wall": rows["t_wall"], "flags": rows["flags"],
            "values": rows["values"], "gaps": gaps_of(rows["seq"]), "stream": head["stream"],
            "frame": head.get("frame", head["stream"])}


def gaps_of(seq: np.ndarray) -> int:
    """Sequence numbers skipped, counted a chunk at a time (overlapping by one)."""
    gaps = 0
    for i in range(0, max(len(seq) - 1, 0), CHUNK_ROWS):
        steps = np.diff(np.asarray(seq[i:i + CHUNK_ROWS + 1], dtype=np.int64))
        gaps += int(np.sum(steps[steps > 1] - 1))
    return gaps


def finish_npz(part: str | Path, npz: str | Path | None = None) -> int:
    """Build the ``.npz`` from a sidecar (by default beside it, ``.part`` removed
    from the name), remove the sidecar, and return the number of samples.

    Each column is copied a chunk at a time (np.savez would hold up to 16 MiB of
    a column), so this too runs in flat memory."""
    import zipfile

    part = Path(part)
    npz = Path(npz) if npz is not None else part.with_suffix("")
    data = load_rows(part)
    with zipfile.ZipFile(npz, "w", allowZip64=True) as zf:
        for key, value in data.items():
            column = np.asarray(value) if not isinstance(value, np.ndarray) else value
            with zf.open(f"{key}.npy", "w", force_zip64=True) as f:
                header = {"descr": np.lib.format.dtype_to_descr(column.dtype), "fortran_order": False,
                          "shape": column.shape}
                np.lib.format.write_array_header_2_0(f, header)
                for i in range(0, max(len(column), 1) if column.ndim else 1, CHUNK_ROWS):
                    f.write(np.ascontiguousarray(column[i:i + CHUNK_ROWS] if column.ndim else column).tobytes())
    part.unlink()
    return len(data["seq"])


def open_writer(path: str | Path, streams: list[str], frames: dict[str, str] | None = None) -> SampleWriter:
    """The writer for a file, by its extension: ``.csv``, ``.npz`` (one stream each) or ``.mcap``;
    ``frames``: each stream's frame (`daemon_frames`), written into the file."""
    suffix = Path(path).suffix.lower()
    if suffix == ".mcap":
        from .ros2mcap import McapWriter
        return McapWriter(path, frames or {})
    if suffix not in (".csv", ".npz"):
        raise ConfigError(f"{path}: record writes .csv, .npz or .mcap (by the file's extension)")
    if len(streams) != 1:
        raise ConfigError(f"{path}: a {suffix} file holds one stream ({len(streams)} given); "
                          "record several into one .mcap, or run one record per stream")
    frame = (frames or {}).get(streams[0])
    return CsvWriter(path, streams[0], frame) if suffix == ".csv" else NpzWriter(path, streams[0], frame)


class Receiver(Protocol):
    def receive(self, timeout_s: float | None = None) -> wire.Sample | None: ...


@dataclass
class Outcome:
    tallies: dict[str, Tally]
    reason: str  # why it stopped: "count", "seconds", "timeout", "stopped"


def record(sub: Receiver, writer: SampleWriter, streams: list[str], *, count: int | None = None,
           seconds: float | None = None, timeout_s: float = 3.0, stop: Callable[[], bool] = lambda: False,
           clock: Callable[[], float] = time.monotonic, flush_every_s: float = FLUSH_EVERY_S) -> Outcome:
    """Write what ``sub`` receives until ``count`` samples (all streams together),
    ``seconds``, ``timeout_s`` without a sample, or ``stop()`` turns true; then
    take what is already queued, and close the writer (the file is complete).

    ``stop`` is looked at least every ``flush_every_s``: a signal handler sets it.
    A write error (a full disk) is raised as an OSError naming the file written.
    """
    try:
        return _record(sub, writer, streams, count, seconds, timeout_s, stop, clock, flush_every_s)
    except OSError as exc:
        if exc.filename is not None or exc.errno is None:
            raise
        # write() and close() name no file (a full disk: "[Errno 28] No space left on device")
        raise OSError(exc.errno, exc.strerror, getattr(writer.file, "name", None)) from exc


def _record(sub: Receiver, writer: SampleWriter, streams: list[str], count: int | None, seconds: float | None,
            timeout_s: float, stop: Callable[[], bool], clock: Callable[[], float], flush_every_s: float) -> Outcome:
    tallies = {s: Tally() for s in streams}
    start = last_sample = last_flush = clock()
    reason = "stopped"

    def take(sample: wire.Sample) -> None:
        writer.write(sample)
        tallies.setdefault(sample.topic, Tally()).add(sample.seq)

    try:
        while True:
            now = clock()
            if stop():
                # Samples already in this process's queue were received: keep them
                # (bounded, as the publisher goes on meanwhile).
                for _ in range(10_000):
                    sample = sub.receive(timeout_s=0)
                    if sample is None:
                        break
                    take(sample)
                break
            if count is not None and sum(t.samples for t in tallies.values()) >= count:
                reason = "count"
                break
            if seconds is not None and now - start >= seconds:
                reason = "seconds"
                break
            if now - last_sample >= timeout_s:
                reason = "timeout"
                break
            wait = min(flush_every_s, timeout_s - (now - last_sample),
                       seconds - (now - start) if seconds is not None else flush_every_s)
            sample = sub.receive(timeout_s=max(wait, 0.0))
            if sample is not None:
                take(sample)
                last_sample = clock()
            if clock() - last_flush >= flush_every_s:
                writer.flush()
                last_flush = clock()
    finally:
        writer.close(tallies)
    return Outcome(tallies, reason)


def summary_line(path: str | Path, outcome: Outcome, stopped_by: str | None = None, verb: str = "wrote") -> str:
    parts = [f"{s}: {t.samples} samples, {t.gaps} missed" + (f" (seq {t.first_seq}-{t.last_seq})" if t.samples else "")
             for s, t in outcome.tallies.items()]
    return f"{verb} {path}: " + "; ".join(parts) + (f" (stopped by {stopped_by})" if stopped_by else "")


class StopOnSignals:
    """While entered, SIGINT, SIGTERM and SIGHUP only note their name (the
    recording loop looks at `is_set`); the previous handlers come back on exit."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)

    def __init__(self) -> None:
        self.name: str | None = None
        self.before: dict[int, Any] = {}

    def _note(self, signum: int, frame: object) -> None:
        self.name = self.name or signal.Signals(signum).name

    def is_set(self) -> bool:
        return self.name is not None

    def __enter__(self) -> StopOnSignals:
        self.before = {s: signal.signal(s, self._note) for s in self.SIGNALS}
        return self

    def __exit__(self, *exc: object) -> None:
        for s, handler in self.before.items():
            signal.signal(s, handler)


def daemon_frames(streams: list[str], endpoint: str | None, control: str | None, timeout_s: float) -> dict[str, str]:
    """Each stream's frame from the daemon's status (asked on ``control``, by
    default beside an ipc ``endpoint``); the stream's name, said on stderr, when
    no daemon answers. A stream that daemon does not publish is refused
    (`ConfigError`, naming those it does)."""
    import sys

    from ..client import ControlClient, control_beside, refuse_unpublished
    from ..errors import FtsensordError
    from .ros2mcap import frames_from_status

    publisher = control_beside(endpoint, control)  # None: the daemon asked may not be the publisher
    try:
        status = ControlClient(publisher or control, timeout_s=timeout_s).status()
    except FtsensordError as exc:
        print(f"ftsensord: {exc}; frame_id: the stream's name", file=sys.stderr)
        status = {}
    if publisher is not None and isinstance(status, dict):
        refuse_unpublished(streams, status, publisher)
    return frames_from_status(status, streams)
