"""The silicone's memory: a Prony series of its stiffness, the creep it makes under a load,
and the recursive filters that run it forwards (the simulator) and backwards (the daemon).

The relaxation modulus, normalised, is G(t)/G(0) = 1 - sum g_i (1 - exp(-t/tau_i)): held at
a deflection the layer's wrench falls from K0 xi to K_inf xi, K_inf = g_inf K0 with
g_inf = 1 - sum g_i. The same series acts on every degree of freedom (docs/design/physics.md).

Held under a load the layer creeps instead. With w_eff = K_inf xi (the wrench a static
calibration's K reads from the deflection: ``stiffness_diag`` is K_inf, the long-term
stiffness), the load w drives it through H(s) = g_inf / G~(s), G~ the series' Laplace form
times s: w_eff = g_inf w + sum_k p_k, rho_k dp_k/dt = c_k w - p_k. Its retardation times
rho_k are longer than the relaxation times (one term: rho = tau / g_inf) and its
coefficients c_k sum to 1 - g_inf, so a held load's w_eff rises from g_inf w to w:
w_eff(t) / w = 1 - sum c_k exp(-t / rho_k).

Both filters update each p_k by its exact exponential over a step: `CreepFilter` for a load
held over each step (the scene's own model: its loads are sampled on a grid), `CreepInverse`
for a load linear between two samples (a sampled, moving load). A few multiplications a
sample and degree of freedom.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

#: The most terms a series may have: three decades of time with one each; more is a fit, not a material.
MAX_TERMS = 4
#: The largest total fraction accepted: at 0.9 the layer would keep a tenth of its stiffness
#: held, far softer than any platinum silicone at small strain (docs/design/physics.md), and the
#: inverse would multiply the noise tenfold.
MAX_TOTAL_FRACTION = 0.9


@dataclass(frozen=True)
class Relaxation:
    """A Prony series: ``fractions`` g_i (each > 0, sum < `MAX_TOTAL_FRACTION`) at
    ``times_s`` tau_i (s, > 0)."""

    fractions: tuple[float, ...]
    times_s: tuple[float, ...]

    def __post_init__(self) -> None:
        g, tau = self.fractions, self.times_s
        if not 1 <= len(g) <= MAX_TERMS or len(tau) != len(g):
            raise ValueError(
                f"a relaxation is 1 to {MAX_TERMS} [fraction, time_s] pairs, got {len(g)} fractions "
                f"and {len(tau)} times"
            )
        if not all(math.isfinite(v) and v > 0 for v in (*g, *tau)):
            raise ValueError(f"fractions and times must be finite and > 0, got {list(zip(g, tau))}")
        if sum(g) >= MAX_TOTAL_FRACTION:
            raise ValueError(
                f"the fractions sum to {sum(g):.3g}: they must sum below {MAX_TOTAL_FRACTION} (the stiffness "
                "left when held is 1 - sum)"
            )
        if len(set(tau)) != len(tau):
            raise ValueError(f"the times must differ, got {list(tau)}")

    @classmethod
    def from_pairs(cls, pairs: object) -> Relaxation:
        """From ``[[fraction, time_s], ...]`` (a scene's or a calibration file's form)."""
        rows = [tuple(float(v) for v in row) for row in pairs]  # type: ignore[attr-defined]
        if any(len(r) != 2 for r in rows):
            raise ValueError(f"each term is [fraction, time_s], got {pairs!r}")
        rows.sort(key=lambda r: r[1])
        return cls(tuple(r[0] for r in rows), tuple(r[1] for r in rows))

    @classmethod
    def from_creep(cls, g_inf: float, c: np.ndarray, rho: np.ndarray) -> Relaxation:
        """The series whose creep is w_eff / w = g_inf + sum c_k (1 - exp(-t/rho_k)) (`creep`'s
        inverse): G~(s) = g_inf / H(s), whose poles -1/tau_i are the roots of H's numerator
        M(s) and residues g_i = -g_inf E(s_i) tau_i / M'(s_i), E = prod(1 + s rho_k)."""
        P = np.polynomial.polynomial
        E = np.array([1.0])
        for r in rho:
            E = P.polymul(E, [1.0, r])
        M = g_inf * E
        for k in range(len(rho)):
            rest = np.array([1.0])
            for j, u in enumerate(rho):
                if j != k:
                    rest = P.polymul(rest, [1.0, u])
            M = P.polyadd(M, c[k] * rest)
        roots = np.sort(P.polyroots(M).real)  # real and negative for positive c (interlacing)
        tau = -1.0 / roots
        g = -g_inf * P.polyval(roots, E) * tau / P.polyval(roots, P.polyder(M))
        order = np.argsort(tau)
        return cls(tuple(float(v) for v in g[order]), tuple(float(v) for v in tau[order]))

    def pairs(self) -> list[list[float]]:
        return [[g, t] for g, t in zip(self.fractions, self.times_s)]

    @property
    def g_inf(self) -> float:
        """K_inf / K0: the stiffness left when held, as a fraction of the instantaneous."""
        return 1.0 - sum(self.fractions)

    def modulus(self, t: np.ndarray | float) -> np.ndarray:
        """G(t) / G(0) at ``t`` (s) after a step of deflection."""
        t = np.asarray(t, dtype=float)[..., None]
        return 1.0 - np.sum(np.array(self.fractions) * (1.0 - np.exp(-t / np.array(self.times_s))), axis=-1)

    @functools.cached_property
    def creep(self) -> tuple[np.ndarray, np.ndarray]:
        """(c_k, rho_k): the creep's coefficients and retardation times (s), longest last.

        H(s) = g_inf D(s) / N(s), D = prod(1 + s tau_i), N = D G~(s)/s's numerator: its roots
        s_k = -1/rho_k are real, negative and interlace the -1/tau_i (a Prony series is a
        completely monotone function), and the residues c_k = g_inf D(s_k) rho_k / N'(s_k)."""
        P = np.polynomial.polynomial
        tau, g = np.array(self.times_s), np.array(self.fractions)
        D = np.array([1.0])
        for t in tau:
            D = P.polymul(D, [1.0, t])
        N = self.g_inf * D
        for i, t in enumerate(tau):
            rest = np.array([1.0])
            for j, u in enumerate(tau):
                if j != i:
                    rest = P.polymul(rest, [1.0, u])
            N = P.polyadd(N, g[i] * P.polymul([0.0, t], rest))
        roots = np.sort(P.polyroots(N).real)  # all real (above); .real drops round-off's imaginary dust
        rho = -1.0 / roots
        c = self.g_inf * P.polyval(roots, D) * rho / P.polyval(roots, P.polyder(N))
        order = np.argsort(rho)
        return c[order], rho[order]

    def creep_response(self, t: np.ndarray | float) -> np.ndarray:
        """w_eff(t) / w under a load w held from t = 0 (K_inf xi(t) / w): the closed form."""
        c, rho = self.creep
        t = np.asarray(t, dtype=float)[..., None]
        return 1.0 - np.sum(c * np.exp(-t / rho), axis=-1)


class CreepFilter:
    """The load's history to w_eff (the simulator's silicone): ``step`` takes the load at a
    step's start, held over ``step_s``. State per term and degree of freedom (``width``)."""

    def __init__(self, relaxation: Relaxation, step_s: float, width: int = 6):
        self.relaxation = relaxation
        self.c, rho = relaxation.creep
        self.rho = rho
        self.step_s = step_s
        self.a = np.exp(-step_s / rho)[:, None]
        self.gain = (self.c * (1.0 - np.exp(-step_s / rho)))[:, None]
        self.p = np.zeros((len(rho), width))

    def settle(self, w: np.ndarray) -> None:
        """The state of ``w`` held for ever (a scene's start: its first load long in place)."""
        self.p = self.c[:, None] * np.asarray(w, dtype=float)

    def output(self, w: np.ndarray) -> np.ndarray:
        """w_eff now, the load now being ``w`` (its instantaneous part g_inf w added)."""
        return self.relaxation.g_inf * w + self.p.sum(axis=0)

    def advance(self, w: np.ndarray, steps: int = 1) -> None:
        """``steps`` steps with the load ``w`` held throughout: exact, in one update."""
        if steps == 1:
            self.p = self.a * self.p + self.gain * w
            return
        a = np.exp(-steps * self.step_s / self.rho)[:, None]
        self.p = a * self.p + (self.c[:, None] * (1.0 - a)) * w


class CreepInverse:
    """w_eff's samples back to the load (the daemon's stage): each sample ``period_s`` after
    the last, the load taken linear between them (first-order hold: exact for a ramp, a
    sinusoid's error second order in the period). ``scale``: w_eff per unit of the wrench
    the estimator reads at long holds (the identified calibration's, 1 for an exact K)."""

    def __init__(self, relaxation: Relaxation, period_s: float, scale: float = 1.0, width: int = 6):
        self.relaxation = relaxation
        c, rho = relaxation.creep
        a = np.exp(-period_s / rho)
        beta = rho * (1.0 - a) / period_s  # the ramp's share: rho/h (1 - a)
        self.c, self.a = c[:, None], a[:, None]
        self.new = (c * (1.0 - beta))[:, None]  # weight of this sample's load in p
        self.old = (c * (beta - a))[:, None]  # ... of the last sample's
        self.denominator = relaxation.g_inf + float(np.sum(c * (1.0 - beta)))
        self.scale = scale
        self.p = np.zeros((len(c), width))
        self.last: np.ndarray | None = None

    def reset(self) -> None:
        """Forget the history: the next sample is taken as a load long held."""
        self.last = None

    def apply(self, y: np.ndarray) -> np.ndarray:
        """The load (same units as ``y``) from this sample's w_eff ``y``."""
        y = np.asarray(y, dtype=float) / self.scale
        if self.last is None:  # after a reset: the load long held (p at its equilibrium)
            self.p = self.c * y
            self.last = y
            return y
        carried = self.a * self.p + self.old * self.last
        w = (y - carried.sum(axis=0)) / self.denominator
        self.p = carried + self.new * w
        self.last = w
        return w

    def peek(self, y: np.ndarray) -> np.ndarray:
        """What `apply` would give for ``y``, the state left as it is (a sample kept out of it)."""
        y = np.asarray(y, dtype=float) / self.scale
        if self.last is None:
            return y
        return (y - (self.a * self.p + self.old * self.last).sum(axis=0)) / self.denominator

    def coast(self) -> None:
        """One period without a sample: the last load taken as held through it (exact for a
        held load: the state relaxes towards its equilibrium)."""
        if self.last is not None:
            self.p = self.a * self.p + (self.c * (1.0 - self.a)) * self.last
