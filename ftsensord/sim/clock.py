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

    ``wait_until`` sleeps most of the way and spins the last ``spin_s``:
    ``time.sleep`` overshoots by tens of microseconds on Linux, as much as a
    whole I2C byte at 400 kHz, so a pure sleep would make the bus look slower
    than it is.
    """

    def __init__(self, spin_s: float = 150e-6):
        self.spin_s = spin_s

    def now(self) -> float:
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            self.wait_until(time.monotonic() + seconds)

    def wait_until(self, t: float) -> None:
        remaining = t - time.monotonic()
        if remaining > self.spin_s:
            time.sleep(remaining - self.spin_s)
        while time.monotonic() < t:
            pass
