"""Optional smoothing of a published wrench: a moving average over N samples,
then a first-order low-pass. The raw flux stream is never filtered.

A filtered output is as good as the inputs in it: it carries the flags of
every input still in its window or still weighing in the low-pass's memory.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from ftsensord.protocol import wire

#: A flagged input's flags stay on the low-pass's output until its weight in the
#: memory, (1 - a)^k, is below this: an input off by the sensor's whole range (50 N)
#: then moves the output by under 5 mN, a fifth of the noise at rest (about 0.025 N).
LOWPASS_FORGET = 1e-4
#: Flags of the cycle, not of the value: a late cycle's wrench is as good as any.
NOT_CARRIED = wire.FLAG_LATE


class WrenchFilter:
    """``averaging`` samples' mean, then y += a (x - y) with a = 1 - exp(-2 pi fc / rate).

    An invalid (NaN) sample passes through and restarts the filter, so a fault
    never smears into the samples after it. A flagged sample that has a value
    enters the filter (restarting on every flag would drop the smoothing whenever
    one chip is briefly missing, and the flags say which samples to distrust), and
    its flags ride on every output it still weighs in: the moving average's window,
    then the low-pass until its weight has decayed below `LOWPASS_FORGET`.
    """

    def __init__(self, averaging: int = 1, lowpass_hz: float = 0.0, rate_hz: float = 100.0):
        self.configure(averaging, lowpass_hz, rate_hz)

    def configure(self, averaging: int, lowpass_hz: float, rate_hz: float) -> None:
        self.averaging = averaging
        self.lowpass_hz = lowpass_hz
        self.alpha = 1.0 if lowpass_hz <= 0 else 1.0 - math.exp(-2 * math.pi * lowpass_hz / rate_hz)
        # alpha == 1 (no low-pass) keeps nothing of the past: the window is the averaging's alone.
        memory = 1 if self.alpha >= 1.0 else math.ceil(math.log(LOWPASS_FORGET) / math.log(1.0 - self.alpha))
        self.reach = averaging - 1 + memory  # how many inputs an output depends on (to LOWPASS_FORGET)
        self.reset()

    def reset(self) -> None:
        self._window: deque[np.ndarray] = deque(maxlen=self.averaging)
        self._flags: deque[int] = deque(maxlen=self.reach)
        self._y: np.ndarray | None = None

    def update(self, w: np.ndarray, flags: int = 0) -> tuple[np.ndarray, int]:
        """The filtered wrench and its flags: ``flags`` (this input's) and those of the
        inputs it still contains."""
        if (
            self.averaging == 1 and self.alpha >= 1.0
        ):  # no averaging, no low-pass (the default): the input itself
            return w, flags
        if not np.isfinite(w).all():
            self.reset()
            return w, flags
        self._window.append(w)
        self._flags.append(flags & ~NOT_CARRIED)
        x = w if self.averaging == 1 else np.mean(self._window, axis=0)
        # No low-pass (alpha 1) keeps nothing of the past: the output is x itself, not y + (x - y).
        self._y = x if self._y is None or self.alpha >= 1.0 else self._y + self.alpha * (x - self._y)
        carried = 0
        for f in self._flags:
            carried |= f
        return self._y, flags | carried
