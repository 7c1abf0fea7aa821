"""The silicone's relaxation, identified from a calibration's step-and-hold segment.

The robot holds one pose, turns to another and holds it (`rig.record_hold`), every chip read
throughout. The static calibration's wrench y(t) = K A (b(t) - zero) then follows the known
load w(t) through the creep of `model.viscoelastic`, times a scale s_d per axis (K was fitted
on readings averaged while the silicone still crept, so it reads a held load s times over;
and each axis has its own static error):

    y_d(t) = s_d g_inf (w_d(t) + sum_k r_k F_k[w_d](t)) + sum_k q_kd exp(-(t - t0)/rho_k) + o_d

with r_k = c_k / g_inf, F_k the response of 1/(1 + s rho_k) to the piecewise-constant load
from rest, q_kd what the poses before the segment left in each term, o_d each axis's offset.
For given times rho_k it is linear in the rest, axis by axis (variable projection): the times
are searched on a grid in log time, refined by zooming in. The same series acts on every axis:
r_k is each axis's ratio, averaged with the weight of what the axis resolves, and s the same
average of the s_d. The creep's (c_k, rho_k) are turned back into the relaxation's
(`Relaxation.from_creep`).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ftsensord.calibration.dataset import Hold
from ftsensord.docfile import Table
from ftsensord.model.viscoelastic import MAX_TOTAL_FRACTION, Relaxation

#: An axis takes part when the segment's step on it is at least this many times its reading
#: noise: below, its creep (a few % of the step) is under the noise of a single reading and
#: the axis adds more noise than creep to the shared fit.
MIN_STEP_TO_NOISE = 20.0
#: The search's grid points per decade of time, and its zoom rounds (each halves the span):
#: 6 a decade puts a point within 20 % of any time, three rounds within 3 %.
POINTS_PER_DECADE, ZOOM_ROUNDS = 6, 3
#: The shortest time searched, as a multiple of the readings' median interval (a faster term is
#: seen by a handful of readings, and the noise makes one of the instantaneous part), and the
#: longest as a share of the hold (a slower one has not shown).
SHORTEST_INTERVALS, LONGEST_HOLD_SHARE = 10.0, 1.0
#: The fit takes every reading of the first seconds after each load (the fast terms live
#: there) and an even pick of the rest up to this many: the least squares' cost is linear
#: in the readings, and 2000 over a minute's hold still resolve a 1 % creep (the readings'
#: noise is a few hundredths of a N each).
FIRST_S, MAX_READINGS = 2.0, 2000
#: A term is kept when it lowers the fit's residual sum of squares (in the readings' noise) by
#: more than this many standard deviations of what noise alone lowers it by: without a creep,
#: that drop is chi-square with the term's parameters as degrees of freedom (its time and, per
#: axis, its rise and its decay), mean df and deviation sqrt(2 df); the search over the
#: term's time makes noise find more than one draw would, hence 5, not 3. Measured on 5
#: axes (df 11, threshold 34): a part without a memory's one term 17 (the packaged part,
#: `ftsensord dataset`'s 60 s hold); the default series' second term over a 12 s hold, 89.
MIN_DROP_DEVIATIONS = 5.0


@dataclass(frozen=True)
class SiliconeCalibration:
    """The identified series, the scale s of the static calibration's K against a load held
    for ever, and the fit's RMS residual as a share of the segment's step."""

    relaxation: Relaxation
    scale: float
    rms_residual: float

    def document(self) -> dict[str, Any]:
        return {"relaxation": self.relaxation.pairs(), "scale": self.scale, "rms_residual": self.rms_residual}

    @classmethod
    def parse(cls, t: Table) -> SiliconeCalibration:
        """A calibration file's ``silicone`` section (`document` writes it)."""
        t.only({"relaxation", "scale", "rms_residual"})
        rows = t.get("relaxation")
        try:
            relaxation = Relaxation.from_pairs(rows)
        except (TypeError, ValueError) as exc:
            raise t.fail(
                "relaxation", f"[[fraction, time_s], ...] pairs of a Prony series ({exc})", rows
            ) from exc
        # 0.5-2: K fitted on creeping readings reads a held load a few % over, never twice.
        return cls(relaxation, t.number("scale", low=0.5, high=2.0), t.number("rms_residual", low=0.0))


def dwell_loads(relaxation: Relaxation, wrench: np.ndarray, times_s: np.ndarray, samples: int) -> np.ndarray:
    """Each pose's load as the silicone carried it (n, 6; N, Nm): the mean of w_eff = K_inf xi
    over the pose's ``samples`` readings, evenly spaced from its first to its last reading,
    each pose's ``wrench`` held from its applied time to the next's (``times_s`` (n, 3), a
    dataset's), the part at rest before the first. A long-held load's is the load itself."""
    c, rho = relaxation.creep
    c = c[:, None]
    p = np.zeros((len(rho), 6))  # each term's part of w_eff (`model.viscoelastic`)
    out = np.empty((len(wrench), 6))
    before, since = np.zeros(6), times_s[0, 0]
    for j, (w, (applied, first, last)) in enumerate(zip(wrench, times_s)):
        p = c * before + (p - c * before) * np.exp(-(applied - since) / rho)[:, None]  # the load before, held
        read = np.linspace(first, last, samples) - applied
        mean_decay = np.exp(-read[:, None] / rho).mean(axis=0)[:, None]
        out[j] = relaxation.g_inf * w + np.sum(c * w + (p - c * w) * mean_decay, axis=0)
        before, since = w, applied
    return out


def settle_s(relaxation: Relaxation, fraction: float) -> float:
    """How long (s) after a load long held comes off its after-effect, the creep's share still
    carried, sum c_k exp(-t / rho_k), takes to fall to ``fraction`` of the load: 0 when it
    starts there. What a robot waits after a load comes off before a no-load pose
    (docs/guide/calibration.md): the after-effect of a load held shorter is smaller."""
    c, rho = relaxation.creep
    left = lambda t: float(np.sum(c * np.exp(-t / rho)))  # noqa: E731
    if left(0.0) <= fraction:
        return 0.0
    low, high = 0.0, float(rho.max())
    while left(high) > fraction:
        high *= 2.0
    for _ in range(60):  # bisection to well under a ms over any span a silicone takes
        mid = 0.5 * (low + high)
        low, high = (mid, high) if left(mid) > fraction else (low, mid)
    return high


def identify(
    hold: Hold, wrench_of: Callable[[np.ndarray], np.ndarray], terms: int = 2
) -> tuple[SiliconeCalibration | None, str]:
    """The silicone's series from ``hold`` with ``wrench_of`` the static calibration's
    wrench of stacked flux (N, Nm); fewer terms when more do not all relax. Returns it, or
    None, with a line for the report saying what was found or why nothing was."""
    t = hold.times_s - hold.load_times_s[0]
    starts = hold.load_times_s - hold.load_times_s[0]
    interval = float(np.median(np.diff(t)))
    y = wrench_of(hold.flux_t)
    # Each axis's reading noise, from successive readings' differences (their median absolute
    # deviation: robust to the step itself; the creep between two readings is far below it).
    diff = np.diff(y, axis=0)
    noise = 1.4826 * np.median(np.abs(diff - np.median(diff, axis=0)), axis=0) / np.sqrt(2.0)
    noise = np.where(noise > 0, noise, np.inf)  # an axis that never moves resolves nothing
    early = np.any((t[:, None] >= starts) & (t[:, None] < starts + FIRST_S), axis=1)
    picked = early | (np.arange(len(t)) % max(1, len(t) // MAX_READINGS) == 0)
    t, y = t[picked], y[picked]
    # A reading stamped at a load's very time was taken before it (the robot moves after a
    # reading ends): "left" puts it in the segment before.
    w = hold.loads[np.clip(np.searchsorted(starts, t, side="left") - 1, 0, None)]
    change = np.ptp(hold.loads, axis=0)
    if not change.max() > 0:  # one load throughout: no step to see creep in
        return None, "the step-and-hold segment's loads do not change: nothing to identify"
    axes = np.flatnonzero(change / noise >= MIN_STEP_TO_NOISE)
    if not len(axes):
        return None, (
            f"the step-and-hold segment's step is below {MIN_STEP_TO_NOISE:g} times the readings' "
            "noise on every axis: nothing to identify"
        )
    jumps = np.diff(np.vstack([np.zeros(6), hold.loads]), axis=0)[:, axes] / noise[axes]
    w, y = w[:, axes] / noise[axes], y[:, axes] / noise[axes]
    step = float(np.mean(change[axes] / noise[axes]))
    low = SHORTEST_INTERVALS * interval
    high = LONGEST_HOLD_SHARE * float(np.min(np.diff(np.append(starts, t[-1]))))
    if high < 10 * low:  # under a decade between the fastest term seen and the hold: no creep to fit
        return None, (
            f"the step-and-hold segment's holds ({high:.3g} s) are under ten times "
            f"{SHORTEST_INTERVALS:g} reading intervals ({low:.3g} s): hold each pose longer"
        )
    snr = change[axes] / noise[axes]
    weight = snr**2 / np.sum(snr**2)  # the better an axis resolves its step, the more it says
    # Terms are added one at a time while each is resolved (`MIN_DROP_DEVIATIONS`) and all relax.
    found: SiliconeCalibration | None = None
    rss = _solve(t, starts, jumps, w, y, np.array([]))[1]  # no creep: each axis's scale and offset
    df = 2 * len(axes) + 1  # a term's parameters: its time, and per axis its rise and its decay
    why = ""
    for n in range(1, terms + 1):
        rho, theta, rms = _search(t, starts, jumps, w, y, n, low, high)
        rss_n = rms**2 * y.size
        # The drop in units of the n-term fit's own residual variance (an F-test's form), so
        # that a noise misjudged by the differences' spread does not decide it.
        drop = (rss - rss_n) / (rss_n / (y.size - n * df - 2 * len(axes)))
        if drop < df + MIN_DROP_DEVIATIONS * np.sqrt(2.0 * df):
            why = (
                f"a term more lowers the residual by {drop:.0f} noise variances, under the "
                f"{df + MIN_DROP_DEVIATIONS * np.sqrt(2.0 * df):.0f} noise alone may"
            )
            break
        # Each axis's own scale (its static error is its own); the creep's shape, c_k / g_inf, shared.
        a0, b = theta[:, 0], theta[:, 1 : 1 + n]
        if not (np.all(a0 > 0) and np.all(weight @ (b / a0[:, None]) > 0)):
            why = f"a fit of {n} terms does not relax"
            break
        ratio = weight @ (b / a0[:, None])
        g_inf = 1.0 / (1.0 + float(ratio.sum()))
        if 1 - g_inf >= MAX_TOTAL_FRACTION:
            why = f"a fit of {n} terms relaxes {100 * (1 - g_inf):.0f} % of the stiffness"
            break
        scale = float(weight @ (a0 + b.sum(axis=1)))
        found = SiliconeCalibration(Relaxation.from_creep(g_inf, ratio * g_inf, rho), scale, rms / step)
        rss = rss_n
    if found is not None:
        return found, (
            f"identified from a {t[-1]:.0f} s step-and-hold ({len(t)} of {len(picked)} readings, axes "
            f"{', '.join(str(a) for a in axes)}): relaxation {found.relaxation.pairs()}, "
            f"scale {found.scale:.4f}, residual {100 * found.rms_residual:.2f} % of the step"
        )
    return None, (
        f"the step-and-hold segment shows no relaxation the readings resolve ({why}): the daemon "
        "applies no creep compensation"
    )


def _search(
    t: np.ndarray,
    starts: np.ndarray,
    jumps: np.ndarray,
    w: np.ndarray,
    y: np.ndarray,
    n: int,
    low: float,
    high: float,
) -> tuple[np.ndarray, np.ndarray, float]:
    """The ``n`` times (s, ascending) within [low, high] that fit best, the linear
    parameters there and the RMS residual (in each axis's noise): a grid, then zoomed in."""
    logs = np.linspace(np.log10(low), np.log10(high), max(2, round(POINTS_PER_DECADE * np.log10(high / low))))
    best: tuple[float, tuple[float, ...]] = (np.inf, ())
    candidates = list(itertools.combinations(logs, n))
    span = float(logs[1] - logs[0])
    for _ in range(ZOOM_ROUNDS + 1):
        for c in candidates:
            rss = _solve(t, starts, jumps, w, y, 10.0 ** np.array(c))[1]
            if rss < best[0]:
                best = (rss, c)
        centre = np.array(best[1])
        offsets = np.array([-span, -span / 2, 0.0, span / 2, span])
        grid = [np.clip(centre[i] + offsets, np.log10(low), np.log10(high)) for i in range(n)]
        candidates = [c for c in itertools.product(*grid) if all(np.diff(c) > 0)]
        span /= 2
    rho = 10.0 ** np.array(best[1])
    theta, rss = _solve(t, starts, jumps, w, y, rho)
    return rho, theta, float(np.sqrt(rss / y.size))


def _solve(
    t: np.ndarray, starts: np.ndarray, jumps: np.ndarray, w: np.ndarray, y: np.ndarray, rho: np.ndarray
) -> tuple[np.ndarray, float]:
    """Least squares of the model at times ``rho``, axis by axis: per axis (a0, b_k..., q_k...,
    o), shape (axes, 2 n + 2), and the residual sum of squares over all axes."""
    m, axes = w.shape
    n = len(rho)
    # F_k of the piecewise-constant load from rest: each jump's exponential rise, summed.
    since = np.clip(t[:, None] - starts[None, :], 0.0, None)  # (m, jumps)
    on = (t[:, None] > starts[None, :]).astype(float)  # as `identify`'s segments: a load acts after its time
    rises = [(on * (1.0 - np.exp(-since / r))) @ jumps for r in rho]  # each (m, axes)
    decay = np.exp(-t[:, None] / rho[None, :])  # (m, n)
    X = np.concatenate(
        [
            np.stack([w.T, *[f.T for f in rises]], axis=-1),  # (axes, m, 2 n + 2)
            np.broadcast_to(np.column_stack([decay, np.ones(m)]), (axes, m, n + 1)),
        ],
        axis=-1,
    )
    # Each axis's normal equations, its columns scaled to unit norm first (the Gram matrix's
    # condition is then that of the columns' shapes, not of their units); batched in einsum: a
    # LAPACK least squares a candidate and axis cost ten times as much on a shared host.
    norm = np.sqrt(np.einsum("amp,amp->ap", X, X))
    Xs = X / norm[:, None, :]
    theta = np.linalg.solve(np.einsum("amp,amq->apq", Xs, Xs), np.einsum("amp,am->ap", Xs, y.T)[..., None])[
        ..., 0
    ]
    theta /= norm
    residual = y.T - np.einsum("amp,ap->am", X, theta)
    return theta, float(np.sum(residual**2))
