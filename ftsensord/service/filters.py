"""Optional smoothing of a published wrench: a moving average over N samples,
then a first-order low-pass. The raw flux stream is never filtered."""

from __future__ import annotations

import math
from collections import deque

import numpy as np


class WrenchFilter:
    """``averaging`` samples' mean, then y += a (x - y) with a = 1 - exp(-2 pi fc / rate).

    An invalid (NaN) sample passes through and restarts the filter, so a fault
    never smears into the samples after it.
    """

    def __init__(self, averaging: int = 1, lowpass_hz: float = 0.0, rate_hz: float = 100.0):
        self.configure(averaging, lowpass_hz, rate_hz)

    def configure(self, averaging: int, lowpass_hz: float, rate_hz: float) -> None:
        self.averaging = averaging
        self.lowpass_hz = lowpass_hz
        self.alpha = 1.0 if lowpass_hz <= 0 else 1.0 - math.exp(-2 * math.pi * lowpass_hz / rate_hz)
        self.reset()

    def reset(self) -> None:
        self._window: deque[np.ndarray] = deque(maxlen=self.averaging)
        self._y: np.ndarray | None = None

    def update(self, w: np.ndarray) -> np.ndarray:
        if not np.all(np.isfinite(w)):
            self.reset()
            return w
        self._window.append(w)
        x = w if self.averaging == 1 else np.mean(self._window, axis=0)
        self._y = x if self._y is None else self._y + self.alpha * (x - self._y)
        return self._y
