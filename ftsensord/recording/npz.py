"""NPZ recordings: rows go to a sidecar ``FILE.npz.part`` as they come (a JSON line, then
fixed-size little-endian records, `_rows_dtype`), and the ``.npz`` is built from it at a clean
end (`finish_npz`); after a kill `load_rows` reads the sidecar. A wrench stream's rows carry
its sigma (``sigma``, n x 6, N and Nm; NaN: unknown or not received)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from ftsensord.errors import ConfigError
from ftsensord.protocol import wire
from ftsensord.recording.columns import SIGMA_COLUMNS, Tally, carries_sigma, value_columns

_NO_SIGMA = np.full(len(SIGMA_COLUMNS), np.nan)  # a sample whose sigma did not come: unknown


def _rows_dtype(count: int, sigma: bool = False) -> np.dtype:
    """A record: i64 seq, f64 t_mono, f64 t_wall, i64 flags, ``count`` f64 values and, with
    ``sigma``, the 6 f64 of the wrench's sigma."""
    fields = [
        ("seq", "<i8"),
        ("t_mono", "<f8"),
        ("t_wall", "<f8"),
        ("flags", "<i8"),
        ("values", "<f8", (count,)),
    ]
    if sigma:
        fields.append(("sigma", "<f8", (len(SIGMA_COLUMNS),)))
    return np.dtype(fields)


class NpzWriter:
    """One stream to ``.npz``, through the sidecar ``<path>.part`` written as rows come."""

    def __init__(self, path: str | Path, stream: str, frame: str | None = None):
        self.path, self.stream, self.frame = Path(path), stream, frame or stream
        self.part = Path(f"{self.path}.part")
        self.file = open(self.part, "wb")
        self.dtype: np.dtype | None = None
        self.sigma = carries_sigma(stream)

    def write(self, sample: wire.Sample) -> None:
        first = self.dtype is None
        if first:
            self.dtype = _rows_dtype(len(sample.values), self.sigma)
            head = {
                "format": "ftsensord-rows",
                "version": 1,
                "stream": self.stream,
                "frame": self.frame,
                "kind": sample.kind,
                "count": len(sample.values),
                "columns": value_columns(self.stream, len(sample.values)),
                "sigma": self.sigma,
            }
            self.file.write(json.dumps(head).encode() + b"\n")
        row = np.zeros((), self.dtype)
        row["seq"], row["t_mono"], row["t_wall"], row["flags"] = (
            sample.seq,
            sample.t_mono,
            sample.t_wall,
            sample.flags,
        )
        row["values"] = sample.values
        if self.sigma:
            row["sigma"] = _NO_SIGMA if sample.sigma is None else sample.sigma
        self.file.write(row.tobytes())
        if first:  # the header on disk at once: killed before the first flush, the file still reads
            self.file.flush()

    def flush(self) -> None:
        self.file.flush()

    def close(self, tallies: dict[str, Tally]) -> None:
        self.file.close()
        if self.dtype is None:  # nothing received: an empty file of the same keys
            arrays: dict[str, Any] = {
                "seq": np.zeros(0, np.int64),
                "t_mono": np.zeros(0),
                "t_wall": np.zeros(0),
                "flags": np.zeros(0, np.int64),
                "values": np.zeros((0, 0)),
                **({"sigma": np.zeros((0, len(SIGMA_COLUMNS)))} if self.sigma else {}),
                "gaps": 0,
                "stream": self.stream,
                "frame": self.frame,
            }
            np.savez(self.path, **arrays)
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
        sigma = bool(head.get("sigma", False))  # absent: a recording made before sigma was recorded
    except (ValueError, KeyError, TypeError) as exc:
        raise ConfigError(f'{part}: not an ftsensord rows sidecar (first line: JSON with "count")') from exc
    dtype = _rows_dtype(count, sigma)
    n = (part.stat().st_size - len(line)) // dtype.itemsize
    rows = np.memmap(part, dtype=dtype, mode="r", offset=len(line), shape=(n,)) if n else np.zeros(0, dtype)
    return {
        "seq": rows["seq"],
        "t_mono": rows["t_mono"],
        "t_wall": rows["t_wall"],
        "flags": rows["flags"],
        "values": rows["values"],
        **({"sigma": rows["sigma"]} if sigma else {}),
        "gaps": gaps_of(rows["seq"]),
        "stream": head["stream"],
        "frame": head.get("frame", head["stream"]),
    }


def gaps_of(seq: np.ndarray) -> int:
    """Sequence numbers skipped, counted a chunk at a time (overlapping by one)."""
    gaps = 0
    for i in range(0, max(len(seq) - 1, 0), CHUNK_ROWS):
        steps = np.diff(np.asarray(seq[i : i + CHUNK_ROWS + 1], dtype=np.int64))
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
                header = {
                    "descr": np.lib.format.dtype_to_descr(column.dtype),
                    "fortran_order": False,
                    "shape": column.shape,
                }
                np.lib.format.write_array_header_2_0(f, header)
                for i in range(0, max(len(column), 1) if column.ndim else 1, CHUNK_ROWS):
                    f.write(
                        np.ascontiguousarray(column[i : i + CHUNK_ROWS] if column.ndim else column).tobytes()
                    )
    part.unlink()
    return len(data["seq"])
