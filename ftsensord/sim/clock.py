"""Clocks for the simulated bus: virtual time for tests, real time for benchmarks.

Both give ``now()`` in seconds and ``sleep(seconds)``; ``wait_until(t)`` is what
the simulated bus uses to spend a transaction's wire time.
"""

from __future__ import annotations

import time


class VirtualClock:
    """Time that moves only when someone sleeps or waits: tests run instantly
    and deterministically."""

    def __init__(self, start: float = 0.0):
        self._now = float(start)

    def now(self) -> float:
        return self._now

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            self._now += seconds

    def wait_until(self, t: float) -> None:
        self._now = max(self._now, t)


class MonotonicClock:
    """The real monotonic clock.

    ``wait_until`` sleeps most of the way and spins the rest: ``time.sleep``
    overshoots by tens of microseconds on Linux (50 us of timer slack for a
    normal thread, a few us under SCHED_FIFO), as much as a whole I2C byte at
    400 kHz, so a pure sleep would make the bus look slower than it is. How long
    to spin is learnt from the sleeps' own overshoots (`SPIN_QUANTILE` of the
    last `SPIN_WINDOW`, plus `SPIN_MARGIN_S`, within ``min_spin_s`` and
    ``spin_s``): a spin is the simulator's CPU, which a board's adapter does not
    burn (its ioctl sleeps), and on a host shared with subscribers it is taken
    from them. A sleep that overshoots more than that ends the wait late: the
    bus is then slower, never faster, than its wire time.
    """

    #: Overshoots kept to learn the spin from: a few cycles' transfers at 100 Hz.
    SPIN_WINDOW = 64
    #: The spin covers this fraction of the recent overshoots (the rest end a wait late).
    SPIN_QUANTILE = 0.95
    #: Added to the learnt overshoot: the spin's own first clock read and loop entry.
    SPIN_MARGIN_S = 10e-6

    def __init__(self, spin_s: float = 150e-6, min_spin_s: float = 20e-6):
        self.spin_s = spin_s  # the most it spins (and what it spins until it has learnt)
        self.min_spin_s = min_spin_s
        self._spin = spin_s
        self._overshoots: list[float] = []

    def now(self) -> float:
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            self.wait_until(time.monotonic() + seconds)

    def wait_until(self, t: float) -> None:
        remaining = t - time.monotonic()
        if remaining > self._spin:
            wake = t - self._spin
            time.sleep(remaining - self._spin)
            self._learn(time.monotonic() - wake)
        while time.monotonic() < t:
            pass

    def _learn(self, overshoot: float) -> None:
        self._overshoots.append(overshoot)
        if len(self._overshoots) >= self.SPIN_WINDOW:
            ranked = sorted(self._overshoots)
            learnt = ranked[int(self.SPIN_QUANTILE * (len(ranked) - 1))] + self.SPIN_MARGIN_S
            self._spin = min(self.spin_s, max(self.min_spin_s, learnt))
            self._overshoots.clear()
