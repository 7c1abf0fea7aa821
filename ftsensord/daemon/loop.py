"""The loop's timing: absolute deadlines, late and skipped cycles, and their statistics.

Cycles start on absolute deadlines k / rate (no drift). A cycle that starts
more than a tenth of a period late is counted late (its samples are flagged);
deadlines already past by a whole period are skipped and counted as missed,
never made up by a burst.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Sequence

import numpy as np
import numpy.ma  # noqa: F401 (np.percentile imports it on its first call: 50 ms, a whole cycle, in the first `status`)
import zmq

from ftsensord.daemon.connections import ConnectionCap
from ftsensord.daemon.control import BUDGET_FRACTION, Budget, Control

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
        self.publish_delays: deque[float] = deque(maxlen=STATS_WINDOW)  # t_mono to the first stream's send
        self._last_seq: int | None = None

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

    def gap(self, seq: int) -> int:
        """How many sequence numbers ``seq``, this cycle's, skips after the last cycle's (0:
        none, the first cycle too; -1: it went back, what came before is unknown)."""
        last, self._last_seq = self._last_seq, seq
        return 0 if last is None else max(-1, seq - last - 1)

    def begin(self, start: float, lateness: float, period_s: float) -> bool:
        """A cycle starts at ``start``, ``lateness`` after its deadline; returns whether it is late."""
        self.starts.append(start)
        self.lateness.append(max(0.0, lateness))
        late = lateness > LATE_FRACTION * period_s
        self.late += late
        return late

    def published(self, delay_s: float) -> None:
        """The first stream's send returned ``delay_s`` after the sample's ``t_mono``."""
        self.publish_delays.append(delay_s)

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


def serve_until(
    control: Control,
    deadline: float,
    period_s: float,
    clock: Callable[[], float],
    sleep: Callable[[float], None],
    stopped: Callable[[], bool],
    caps: Sequence[ConnectionCap] = (),
) -> None:
    """Answer control requests until ``deadline`` (s on ``clock``), then return.

    The loop comes first: this cycle's control work has a `Budget` (MAX_PER_CYCLE
    requests, BUDGET_FRACTION of the period, at least one request), shared in turn
    among clients; what does not fit waits for the next cycle, however many clients
    flood the socket. Waiting ends with ``sleep``, the bus's: the loop's clock is the
    bus's (virtual in tests, so a test can run this very code). Each ``caps``' surplus
    connections are shut down as they come (`ConnectionCap`), whatever the budget: a
    connection costs a descriptor whether or not it is served."""
    poller = zmq.Poller()
    socket = control.socket
    if socket is not None:
        poller.register(socket, zmq.POLLIN)
    for cap in caps:
        poller.register(cap.monitor, zmq.POLLIN)
    budget = Budget(seconds=min(BUDGET_FRACTION * period_s, deadline - clock()))
    spent = False
    while not stopped():
        for cap in caps:
            cap.drain()
        if not spent:
            spent = control.serve_waiting(budget)
        remaining = deadline - clock()
        if remaining <= 0:
            return
        # Budget spent: the requests left stay queued, and a poll would return at once
        # for them and spin; so sleep. Else wait for a request until 1 ms before.
        if (
            not spent
            and socket is not None
            and remaining > 2e-3
            and poller.poll(timeout=int((remaining - 1e-3) * 1000))
        ):
            continue
        remaining = deadline - clock()
        if remaining > 0:
            sleep(min(remaining, 0.05))  # short steps: a signal stops the loop
