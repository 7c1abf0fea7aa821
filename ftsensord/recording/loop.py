"""The recording loop: `open_writer` by the file's extension, `record` until a count, a
time, a silence or a stop signal (`StopOnSignals`), the frames from the daemon
(`daemon_frames`) and the summary line."""

from __future__ import annotations

import signal
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from ftsensord.errors import ConfigError
from ftsensord.protocol import wire
from ftsensord.recording.columns import Tally
from ftsensord.recording.csvfile import CsvWriter
from ftsensord.recording.npz import NpzWriter

#: Longest a received sample waits in the process before it is handed to the
#: kernel: half the one second a kill may cost, so a slow flush still meets it.
FLUSH_EVERY_S = 0.5


class SampleWriter(Protocol):
    file: Any  # the open file the rows go to (named when writing it fails)

    def write(self, sample: wire.Sample) -> None: ...
    def flush(self) -> None: ...
    def close(self, tallies: dict[str, Tally]) -> None: ...


def open_writer(path: str | Path, streams: list[str], frames: dict[str, str] | None = None) -> SampleWriter:
    """The writer for a file, by its extension: ``.csv``, ``.npz`` (one stream each) or ``.mcap``;
    ``frames``: each stream's frame (`daemon_frames`), written into the file."""
    suffix = Path(path).suffix.lower()
    if suffix == ".mcap":
        from ftsensord.recording.ros2mcap import McapWriter

        return McapWriter(path, frames or {})
    if suffix not in (".csv", ".npz"):
        raise ConfigError(f"{path}: record writes .csv, .npz or .mcap (by the file's extension)")
    if len(streams) != 1:
        raise ConfigError(
            f"{path}: a {suffix} file holds one stream ({len(streams)} given); "
            "record several into one .mcap, or run one record per stream"
        )
    frame = (frames or {}).get(streams[0])
    return CsvWriter(path, streams[0], frame) if suffix == ".csv" else NpzWriter(path, streams[0], frame)


class Receiver(Protocol):
    def receive(self, timeout_s: float | None = None) -> wire.Sample | None: ...


@dataclass
class Outcome:
    tallies: dict[str, Tally]
    reason: str  # why it stopped: "count", "seconds", "timeout", "stopped"


def record(
    sub: Receiver,
    writer: SampleWriter,
    streams: list[str],
    *,
    count: int | None = None,
    seconds: float | None = None,
    timeout_s: float = 3.0,
    stop: Callable[[], bool] = lambda: False,
    clock: Callable[[], float] = time.monotonic,
    flush_every_s: float = FLUSH_EVERY_S,
) -> Outcome:
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


def _record(
    sub: Receiver,
    writer: SampleWriter,
    streams: list[str],
    count: int | None,
    seconds: float | None,
    timeout_s: float,
    stop: Callable[[], bool],
    clock: Callable[[], float],
    flush_every_s: float,
) -> Outcome:
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
            wait = min(
                flush_every_s,
                timeout_s - (now - last_sample),
                seconds - (now - start) if seconds is not None else flush_every_s,
            )
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


def summary_line(
    path: str | Path, outcome: Outcome, stopped_by: str | None = None, verb: str = "wrote"
) -> str:
    parts = [
        f"{s}: {t.samples} samples, {t.gaps} missed"
        + (f" (seq {t.first_seq}-{t.last_seq})" if t.samples else "")
        for s, t in outcome.tallies.items()
    ]
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


def daemon_frames(
    streams: list[str], endpoint: str | None, control: str | None, timeout_s: float
) -> dict[str, str]:
    """Each stream's frame from the daemon's status (asked on ``control``, by
    default beside an ipc ``endpoint``); the stream's name, said on stderr, when
    no daemon answers. A stream that daemon does not publish is refused
    (`ConfigError`, naming those it does)."""
    import sys

    from ftsensord.client import ControlClient, control_beside, refuse_unpublished
    from ftsensord.errors import FtsensordError
    from ftsensord.recording.ros2mcap import frames_from_status

    publisher = control_beside(endpoint, control)  # None: the daemon asked may not be the publisher
    try:
        status = ControlClient(publisher or control, timeout_s=timeout_s).status()
    except FtsensordError as exc:
        print(f"ftsensord: {exc}; frame_id: the stream's name", file=sys.stderr)
        status = {}
    if publisher is not None and isinstance(status, dict):
        refuse_unpublished(streams, status, publisher)
    return frames_from_status(status, streams)
