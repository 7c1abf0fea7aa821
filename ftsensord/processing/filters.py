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
        self.factors = variance_factors(averaging, self.alpha)
        self.reset()

    def reset(self) -> None:
        self._window: deque[np.ndarray] = deque(maxlen=self.averaging)
        self._flags: deque[int] = deque(maxlen=self.reach)
        self._y: np.ndarray | None = None
        self._inputs = 0  # since the reset: the output's variance factor is `factors`' entry for it

    def variance_factor(self) -> float:
        """The last output's variance over one input's, for inputs of independent noise of
        equal variance (`variance_factors`): 1 unfiltered, and right after a reset."""
        factors = self.factors
        n = self._inputs
        return 1.0 if n == 0 else factors[min(n, len(factors)) - 1]

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
        self._inputs += 1
        self._flags.append(flags & ~NOT_CARRIED)
        x = w if self.averaging == 1 else np.mean(self._window, axis=0)
        # No low-pass (alpha 1) keeps nothing of the past: the output is x itself, not y + (x - y).
        self._y = x if self._y is None or self.alpha >= 1.0 else self._y + self.alpha * (x - self._y)
        carried = 0
        for f in self._flags:
            carried |= f
        return self._y, flags | carried


#: `variance_factors` stops once a step changes the factor by less than this fraction
#: (the rest of the low-pass's start-up moves it by less than 1e-4 of itself, 5e-5 of a sigma),
VARIANCE_SETTLED = 1e-6
#: ...or after this many inputs (a 0.05 Hz low-pass at 1 kHz), where it keeps the last
#: factor, which is above the steady one: the sigma errs on the large side.
VARIANCE_STEPS = 20000


def variance_factors(averaging: int, alpha: float) -> list[float]:
    """The filter's output variance over one input's, for inputs of independent noise of one
    variance, after 1, 2, ... inputs since a reset (the last entry holds from then on).

    The moving average of n <= ``averaging`` inputs, m_k, then y_1 = m_1, y_k = y_(k-1) +
    ``alpha`` (m_k - y_(k-1)): y_k is a sum of weights times inputs, and its variance factor the
    sum of their squares. The recursion keeps the weights on the last ``averaging`` inputs
    (r) and the sum of all (V): the older ones only decay by (1 - alpha). Without the low-pass
    it ends at 1 / averaging; without averaging at alpha / (2 - alpha) = (1 - a) / (1 + a), a =
    exp(-2 pi fc / rate)."""
    N = max(1, int(averaging))
    if alpha >= 1.0:
        return [1.0 / min(k, N) for k in range(1, N + 1)]
    keep = 1.0 - alpha
    if N == 1:  # the low-pass alone: V_k = b^(k-1) + alpha^2 (1 - b^(k-1)) / (1 - b), b = (1 - alpha)^2
        b = keep**2
        steady = alpha / (2.0 - alpha)
        # until b^(k-1) (1 - steady) is VARIANCE_SETTLED of the steady factor
        steps = min(VARIANCE_STEPS, 2 + math.ceil(math.log(VARIANCE_SETTLED * steady) / math.log(b)))
        powers = b ** np.arange(steps)
        return (powers + steady * (1.0 - powers)).tolist()
    r = np.zeros(N)
    V = 0.0
    out: list[float] = []
    for k in range(1, VARIANCE_STEPS + 1):
        n = min(k, N)
        a = np.zeros(N)
        a[:n] = 1.0 / n
        if k == 1:
            new = a
            V_new = float(new @ new)
        else:
            new = alpha * a
            new[1:] += keep * r[:-1]
            V_new = float(new @ new) + keep**2 * (V - float(r[:-1] @ r[:-1]))
        r, previous, V = new, V, V_new
        out.append(V)
        if k > N and abs(V - previous) <= VARIANCE_SETTLED * V:
            break
    return out
