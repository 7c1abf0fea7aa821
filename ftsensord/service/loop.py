"""The loop's timing: absolute deadlines, late and skipped cycles, and their statistics.

Cycles start on absolute deadlines k / rate (no drift). A cycle that starts
more than a tenth of a period late is counted late (its samples are flagged);
deadlines already past by a whole period are skipped and counted as missed,
never made up by a burst.
"""

from __future__ import annotations

from collections import deque

import numpy as np

#: A cycle starting later than this fraction of a period after its deadline is late.
LATE_FRACTION = 0.1
#: Cycles kept for the achieved rate and the jitter percentiles (10 s at 100 Hz).
STATS_WINDOW = 1000


class LoopTiming:
    """Counts what the loop's deadlines came to; times in s on the loop's monotonic clock."""

    def __init__(self) -> None:
        self.cycles = self.missed = self.late = 0
        self.starts: deque[float] = deque(maxlen=STATS_WINDOW)
        self.lateness: deque[float] = deque(maxlen=STATS_WINDOW)
        self.durations: deque[float] = deque(maxlen=STATS_WINDOW)  # a cycle's start to its last publish

    def skip_missed(self, deadline: float, now: float, period_s: float) -> tuple[float, float]:
        """The deadline to run now and its lateness: deadlines a whole period or more
        behind are dropped (counted missed), never made up."""
        lateness = now - deadline
        if lateness >= period_s:
            skipped = int(lateness // period_s)
            self.missed += skipped
            deadline += skipped * period_s
            lateness -= skipped * period_s
        return deadline, lateness

    def begin(self, start: float, lateness: float, period_s: float) -> bool:
        """A cycle starts at ``start``, ``lateness`` after its deadline; returns whether it is late."""
        self.starts.append(start)
        self.lateness.append(max(0.0, lateness))
        late = lateness > LATE_FRACTION * period_s
        self.late += late
        return late

    def end(self, duration_s: float) -> None:
        self.durations.append(duration_s)
        self.cycles += 1

    def achieved_rate_hz(self) -> float | None:
        if len(self.starts) < 2 or self.starts[-1] == self.starts[0]:
            return None
        return (len(self.starts) - 1) / (self.starts[-1] - self.starts[0])


def percentiles_us(seconds: deque[float]) -> dict[str, float]:
    """p50, p99 and max of durations in s, in us (zeros before the first cycle)."""
    us = np.array(seconds) * 1e6 if seconds else np.zeros(1)
    return {"p50": float(np.percentile(us, 50)), "p99": float(np.percentile(us, 99)), "max": float(us.max())}
