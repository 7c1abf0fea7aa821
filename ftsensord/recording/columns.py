"""What every recording format shares: a stream's column names and the tally of what it gave."""

from __future__ import annotations

from dataclasses import dataclass

WRENCH_COLUMNS = ["fx_N", "fy_N", "fz_N", "mx_Nm", "my_Nm", "mz_Nm"]
#: A wrench's 1-sigma per axis, recorded beside it (its companion stream, `wire.KIND_SIGMA`).
SIGMA_COLUMNS = ["sigma_" + c for c in WRENCH_COLUMNS]


@dataclass
class Tally:
    """What one stream gave a recording: samples, and sequence numbers skipped."""

    samples: int = 0
    gaps: int = 0
    first_seq: int | None = None
    last_seq: int | None = None

    def add(self, seq: int) -> None:
        if self.last_seq is not None and seq > self.last_seq + 1:
            self.gaps += seq - self.last_seq - 1
        self.first_seq = seq if self.first_seq is None else self.first_seq
        self.last_seq = seq
        self.samples += 1


def value_columns(stream: str, count: int) -> list[str]:
    """Column names of a stream's values: the wrench's (N, Nm), a wrench's sigma (a
    ``sigma/wrench/...`` stream recorded on its own: N, Nm), or each chip's flux (T)."""
    if stream.startswith("wrench/"):
        return WRENCH_COLUMNS
    if stream.startswith("sigma/"):
        return SIGMA_COLUMNS
    return [f"b{i // 3}{'xyz'[i % 3]}_T" for i in range(count)]


def carries_sigma(stream: str) -> bool:
    """Whether a stream's recording has its sigma beside each sample: a wrench stream's
    (`SIGMA_COLUMNS`; unknown or not received: NaN, or an empty CSV cell)."""
    return stream.startswith("wrench/")
