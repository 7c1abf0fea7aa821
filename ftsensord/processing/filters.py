"""Optional smoothing of a published wrench: a moving average over N samples,
then a first-order low-pass. The raw flux stream is never filtered.

A filtered output is as good as the inputs in it: it carries the flags of
every input still in its window or still weighing in the low-pass's memory.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

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
        self.variance = variance_factors(averaging, self.alpha)
        # The steady factor last (what `status` reports once settled); `variance_factor` asks `variance`.
        self.factors = [*self.variance.head, self.variance.steady]
        self.reset()

    def reset(self) -> None:
        self._window: deque[np.ndarray] = deque(maxlen=self.averaging)
        self._flags: deque[int] = deque(maxlen=self.reach)
        self._y: np.ndarray | None = None
        self._inputs = 0  # since the reset: the output's variance factor is `factors`' entry for it

    def variance_factor(self) -> float:
        """The last output's variance over one input's, for inputs of independent noise of
        equal variance (`variance_factors`): 1 unfiltered, and right after a reset."""
        n = self._inputs
        return 1.0 if n == 0 else self.variance.at(n)

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


@dataclass(frozen=True)
class VarianceFactors:
    """The filter's output variance over one input's after n inputs since a reset (`at`):
    ``head`` after 1 .. len(head) inputs, exact; from then on ``steady`` + (head[-1] - steady)
    ``decay``^(n - len(head)), exact too (`variance_factors`)."""

    head: tuple[float, ...]
    steady: float
    decay: float  # (1 - alpha)^2 a input: the low-pass's memory of the start-up, squared

    def at(self, n: int) -> float:
        """After ``n`` >= 1 inputs."""
        head = self.head
        if n <= len(head):
            return head[n - 1]
        return self.steady + (head[-1] - self.steady) * self.decay ** (n - len(head))


def variance_factors(averaging: int, alpha: float) -> VarianceFactors:
    """The filter's output variance over one input's, for inputs of independent noise of one
    variance, after n inputs since a reset.

    The moving average of n <= ``averaging`` = N inputs, m_k, then y_1 = m_1, y_k = y_(k-1) +
    ``alpha`` (m_k - y_(k-1)), b = 1 - alpha: y_k is a sum of weights w_kj times inputs, its
    factor V_k the sum of their squares, and w_k = b w_(k-1) + alpha a_k (a_k the window's
    1 / min(k, N) each), so

        V_k = b^2 V_(k-1) + 2 alpha b <w_(k-1), a_k> + alpha^2 / min(k, N),

    where <w_(k-1), a_k> = 1/k while the window fills (the weights sum to 1), then (1 - O)/N,
    O the weight on the inputs that have left the window: O and the one weight it needs
    follow scalar recurrences of their own, so the 2N start-up steps cost a few float
    operations each (0.2 ms at N = 100, 40 ms at the largest averaging, 10000), whatever the
    low-pass. From k = 2N - 1 on, every input's weight in y_k is the steady filter's times a
    power of b, and V_k - V_inf = C b^(2k) exactly, with the steady factor

        V_inf = [sum_(m=1..N) (1 - b^m)^2 + (1 - b^N)^2 b^2 / (alpha (2 - alpha))] / N^2

    (the steady weights (1 - b^(d+1)) / N at lag d < N, b^(d-N+1) (1 - b^N) / N beyond; each
    term positive and 1 - b^m taken as -expm1, so that the cutoff -> 0, alpha -> 0, loses
    nothing to cancellation: V_inf -> alpha / 2 -> 0). Without the low-pass it ends at 1 / N,
    without averaging at alpha / (2 - alpha) = (1 - a) / (1 + a), a = exp(-2 pi fc / rate)."""
    N = max(1, int(averaging))
    if alpha >= 1.0:  # no low-pass: the window's mean alone
        return VarianceFactors(tuple(1.0 / min(k, N) for k in range(1, N + 1)), 1.0 / N, 0.0)
    b = 1.0 - alpha
    one = -np.expm1(np.arange(1, N + 1) * math.log1p(-alpha))  # 1 - b^m, m = 1..N
    steady = (float(one @ one) + float(one[-1]) ** 2 * b * b / (alpha * (2.0 - alpha))) / N**2
    if N == 1:  # V_k = b^(2(k-1)) + steady (1 - b^(2(k-1))): the tail's form from the first input
        return VarianceFactors((1.0,), steady, b * b)
    head = [1.0]
    V, first, gone, P = (
        1.0,
        1.0,
        0.0,
        0.0,
    )  # gone: O below; first: w_(k,1) while k < N; P: w_(k-1, k+1-N) from k = N
    kept = b ** (N - 2)  # an input's weight in a window's term, N - 2 steps after that window
    for k in range(2, 2 * N + 1):
        G = 1.0 / k if k <= N else (1.0 - gone) / N
        V = b * b * V + 2.0 * alpha * b * G + alpha * alpha / min(k, N)
        if k < N:
            first = b * first + alpha / k
        elif k == N:
            P = first
            gone = b * P + alpha / N
        else:
            left = k - N  # the input that left the window
            P = b * (P - (alpha if left >= 2 else 1.0) * kept / left) + alpha / N
            gone = b * (gone + P) + alpha / N
        head.append(V)
    return VarianceFactors(tuple(head), steady, b * b)
