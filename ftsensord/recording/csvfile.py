"""CSV recordings: the samples in ``FILE.csv``, what they are in ``FILE.csv.json``.

The CSV's first line is its column names and every other line a sample, so the usual
readers take it with their defaults (``csv.DictReader``, ``pandas.read_csv``,
``numpy.genfromtxt(..., delimiter=",", names=True)``): a comment line above the names,
as the format once had, gave each of them nothing or junk.

What the rows cannot say (stream, frame, units, what the flag bits mean, how many
samples were received and missed, a write error) is in the sidecar ``FILE.csv.json``,
one JSON object padded with spaces to `META_WIDTH` bytes. It is written and handed to
the kernel before the first row, so a recorder killed outright leaves it as the CSV
(``"state": "recording"``: `read_meta` then counts the CSV's rows), and it is
rewritten in place at the end, in one write of the same length: that takes no new
block, so it is written on a full disk too, when it must tell the true count.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from ftsensord.errors import ConfigError
from ftsensord.protocol import wire
from ftsensord.recording.columns import SIGMA_COLUMNS, Tally, carries_sigma, value_columns

FORMAT = "ftsensord-csv"
#: The sidecar's size, one file-system block: the JSON is padded to it so that every
#: rewrite is in place (the longest, a flux stream's with a torn row kept, is under 3 kB).
META_WIDTH = 4096
#: Longest error text and torn row kept in the sidecar, so its JSON fits `META_WIDTH`.
MAX_KEPT_CHARS = 1000
TIME_UNITS = {
    "seq": "the daemon's cycle number (a jump: samples missed)",
    "t_mono_s": "s, CLOCK_MONOTONIC of the daemon's host, when the cycle's data were in hand",
    "t_wall_s": "s, Unix time (UTC), the same moment",
    "flags": "bit field, the sum of the flag_bits of the conditions that held (docs/reference/protocol.md)",
}
VALUE_UNITS = {"_N": "N", "_Nm": "Nm", "_T": "T"}
SIGMA_UNIT = (
    "{unit}, the daemon's 1-sigma of {column} (docs/reference/protocol.md, Each sample's sigma); "
    "nan: the daemon does not know it; empty: not received"
)


def meta_path(csv: str | Path) -> Path:
    """The sidecar of a CSV recording: ``FILE.csv.json`` beside ``FILE.csv``."""
    return Path(f"{csv}.json")


def _units(columns: list[str]) -> dict[str, str]:
    units = {c: TIME_UNITS.get(c) or VALUE_UNITS["_" + c.rsplit("_", 1)[1]] for c in columns}
    for c in columns:
        if c.startswith("sigma_") and c.removeprefix("sigma_") in columns:  # beside its wrench's column
            units[c] = SIGMA_UNIT.format(unit=units[c], column=c.removeprefix("sigma_"))
    return units


_NO_SIGMA = "," * len(SIGMA_COLUMNS)  # six empty cells: the sample's sigma did not come


class CsvWriter:
    """One stream to CSV, a row per sample, its names on the first line; the sidecar
    ``FILE.csv.json`` says what the rows are and, at the end, how many."""

    def __init__(self, path: str | Path, stream: str, frame: str | None = None):
        self.path, self.stream = Path(path), stream
        self.meta: dict[str, Any] = {
            "format": FORMAT,
            "version": 1,
            "csv": self.path.name,
            "stream": stream,
            "frame": frame or stream,
            "kind": stream.split("/", 1)[0] if stream.startswith(("wrench/", "sigma/")) else "flux",
            "columns": None,
            "units": None,
            "flag_bits": {name: bit for bit, name in wire.FLAG_NAMES.items()},
            "state": "recording",
            "samples": None,
            "received": None,
            "missed": None,
            "first_seq": None,
            "last_seq": None,
            "error": None,
            "torn_row": None,
        }
        self.sigma = carries_sigma(stream)  # the six sigma columns after the wrench's
        self.file = open(self.path, "w", encoding="ascii")
        self.meta_file = open(meta_path(self.path), "wb")
        self._write_meta()
        self.columns_written = False
        self.error: OSError | None = None  # the first write error (a full disk): the rows written are counted

    def _write_meta(self) -> None:
        text = json.dumps(self.meta, indent=1)
        if len(text) >= META_WIDTH:  # not met with this module's columns; a torn row is the first to go
            self.meta["torn_row"] = "(dropped: too long for the sidecar)"
            text = json.dumps(self.meta, indent=1)[: META_WIDTH - 1]
        self.meta_file.seek(0)
        self.meta_file.write(text.ljust(META_WIDTH - 1).encode("ascii", "replace") + b"\n")
        self.meta_file.flush()

    def write(self, sample: wire.Sample) -> None:
        try:
            if not self.columns_written:
                columns = [
                    "seq",
                    "t_mono_s",
                    "t_wall_s",
                    "flags",
                    *value_columns(self.stream, len(sample.values)),
                    *(SIGMA_COLUMNS if self.sigma else []),
                ]
                self.file.write(",".join(columns) + "\n")
                self.columns_written = True
                self.meta["columns"], self.meta["units"] = columns, _units(columns)
                self._write_meta()
            sigma = ""
            if self.sigma:
                sigma = (
                    _NO_SIGMA if sample.sigma is None else "," + ",".join(f"{v:.9g}" for v in sample.sigma)
                )
            self.file.write(
                f"{sample.seq},{sample.t_mono:.6f},{sample.t_wall:.6f},{sample.flags},"
                + ",".join(f"{v:.9g}" for v in sample.values)
                + sigma
                + "\n"
            )
        except OSError as exc:
            self.error = self.error or exc
            raise

    def flush(self) -> None:
        try:
            self.file.flush()
        except OSError as exc:
            self.error = self.error or exc
            raise

    def close(self, tallies: dict[str, Tally]) -> None:
        """Complete the recording: the sidecar says how many samples the CSV holds. After a
        write error (a disk full) the CSV's rows are counted, a torn last one cut off (kept
        in the sidecar) so that every reader reads the rest, and the error raised again:
        the tally counts samples received, not written."""
        t = tallies.get(self.stream, Tally())
        self.meta.update(received=t.samples, missed=t.gaps, first_seq=t.first_seq, last_seq=t.last_seq)
        if self.error is None:
            try:
                self.flush()
                self.file.close()
                self.meta.update(state="complete", samples=t.samples)
                self._write_meta()
                self.meta_file.close()
                return
            except OSError as exc:
                self.error = self.error or exc
        error = self.error
        assert error is not None  # set by whichever write, flush or close failed
        try:
            self.file.close()  # the fd is closed even when the flush of what is left fails again
        except OSError:
            pass
        rows, complete, size = csv_rows(self.path)
        torn = None
        if size > complete:
            with open(self.path, "rb") as f:
                f.seek(complete)
                torn = f.read(MAX_KEPT_CHARS).decode("ascii", "replace")
            os.truncate(self.path, complete)  # frees blocks: possible on a full disk
        self.meta.update(
            state="write error",
            samples=rows,
            error=(error.strerror or str(error))[:MAX_KEPT_CHARS],
            torn_row=torn,
        )
        try:
            self._write_meta()
            self.meta_file.close()
        except OSError:
            pass  # the error the caller must hear of is the first
        raise error


def csv_rows(path: str | Path) -> tuple[int, int, int]:
    """A CSV recording's complete data rows (after its column names), the byte at which
    they end, and the file's size (more: a torn row follows)."""
    lines, end, size = 0, 0, 0
    with Path(path).open("rb") as f:
        while chunk := f.read(1 << 20):  # a day's record is gigabytes: counted a megabyte at a time
            lines += chunk.count(b"\n")
            last = chunk.rfind(b"\n")
            end = size + last + 1 if last >= 0 else end
            size += len(chunk)
    return max(0, lines - 1), end, size


def read_meta(csv: str | Path) -> dict[str, Any]:
    """What a CSV recording's sidecar says: stream, frame, kind, columns, units,
    flag_bits, state (``complete``, ``write error``, or ``recording``: the recorder
    was killed), samples (the CSV's rows), received, missed, first_seq, last_seq,
    error, torn_row (a write error's cut-off last row).

    After a kill ``samples`` is counted in the CSV, and ``torn_row`` is the text of
    a row the kill tore (still in the CSV, which the reader then skips or pads)."""
    meta_file = meta_path(csv)
    try:
        meta = json.loads(meta_file.read_bytes())
    except FileNotFoundError as exc:
        raise ConfigError(
            f"{meta_file}: missing: `ftsensord record` writes it beside {Path(csv).name}"
        ) from exc
    except ValueError as exc:
        raise ConfigError(
            f"{meta_file}: not JSON: expected the sidecar of an ftsensord CSV recording"
        ) from exc
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise ConfigError(
            f'{meta_file}: not an ftsensord CSV sidecar (expected a JSON object with "format": "{FORMAT}")'
        )
    if meta.get("state") == "recording":
        rows, complete, size = csv_rows(csv)
        meta["samples"] = rows
        if size > complete:
            with Path(csv).open("rb") as f:
                f.seek(complete)
                meta["torn_row"] = f.read(MAX_KEPT_CHARS).decode("ascii", "replace")
    return meta
