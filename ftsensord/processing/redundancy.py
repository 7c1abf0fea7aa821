"""The redundancy check: which of a sensor's chips agree with one deflection, sample by
sample (`LinearModel.consistency`), which were found out, and when they may rejoin. The
pipeline (`pipeline.SensorPipeline`) asks it for the chips to estimate from.
"""

from __future__ import annotations

import functools
import math
from typing import Protocol

import numpy as np

from ftsensord.model.consistency import Consistency, FoldedCheck, chi2_quantile
from ftsensord.model.linear import EXTRAPOLATION_MARGIN, SENSOR_RANGE, LinearModel
from ftsensord.processing.temperature import ThermalCompensation
from ftsensord.protocol import wire


class Checked(Protocol):
    """What the check reads of the sensor it checks (`pipeline.SensorPipeline` is one): its
    linear model with its zero, each channel's noise (T), the temperature stage (None: off),
    the wrench the tare removed (N, Nm), the calibration's loads (N, Nm; None: unknown), and
    how many chips may be left out."""

    model: LinearModel
    sigma_t: np.ndarray | None
    thermal: ThermalCompensation | None
    tare_wrench: np.ndarray
    max_missing_chips: int
    version: int  # moves whenever the model's zero or the tare's wrench does

    @property
    def wrench_range(self) -> np.ndarray | None: ...


#: The redundancy check (`LinearModel.consistency`), two tests on the whitened residual:
#: the whole residual (chi-square, 3 n - 6 dof: any disagreement, e.g. a field two chips
#: see) and, per chip, how much it drops when that chip is left out (chi-square, 3 dof: the
#: likelihood-ratio test for one faulty chip, far more sensitive to one, as its 3 dof hold
#: less noise and a fifth of the model error), and the slow test below. Under noise alone a
#: sample fails any with these odds in all (half to the whole residual's test, a quarter to
#: each per-chip test, split among the chips): at
#: 2 sensors x 100 Hz a false alarm once in 58 days, and it costs one flagged sample
#: estimated from 7 chips.
CONSISTENCY_FALSE_ODDS = 1e-9
#: The linear model's own residual (whitened norm, in noise sigmas), which the noise
#: threshold is raised by: at most AT_REST + AT_RANGE * s^2 for a load s times the
#: calibration's largest (the largest ratio over the axes). Measured on the nominal scene
#: with both shipped calibrations (600 loads at each s, tests/test_consistency.py measures
#: it again). Whole residual: 2.0 at rest (the calibration's zero is 4 uT off the scene's),
#: 3.6 at s = 0.25, 6.4 at 0.5, 20.3 at 1, 48.5 at 1.5. Largest one-chip drop: 1.0 at
#: rest, 1.3 at 0.1, 1.9 at 0.25, 3.8 at 0.5, 11.3 at 1, 27.6 at 1.5. The bounds below
#: clear each by at least 11 %. A real sensor's calibration with a larger model error
#: needs larger ones.
MODEL_RESIDUAL_AT_REST, MODEL_RESIDUAL_AT_RANGE = 2.5, 26.0
CHIP_RESIDUAL_AT_REST, CHIP_RESIDUAL_AT_RANGE = 1.5, 13.0
#: With `stray_field = "gradient"` a third test: the estimated gradient (chi-square, 2 dof),
#: which takes half of the whole residual's odds. Its model allowance, measured the same way
#: (tests/test_stray.py, the larger of the two calibrations): 0.08 sigma at rest, 0.2 at
#: s = 0.1, 0.6 at 0.25, 1.9 at 0.5, 8.0 at 1, 18.4 at 1.5; the bounds clear each by 18 %.
GRADIENT_RESIDUAL_AT_REST, GRADIENT_RESIDUAL_AT_RANGE = 0.3, 9.5
#: A chip found disagreeing stays out (its samples flagged) until it has agreed this many
#: samples in a row at a looser limit, the noise's 1 % point: a stuck chip under a slow
#: load hovers at the threshold for a while, and in and out it would let samples through
#: that are nearly as wrong as the threshold allows.
REJOIN_SAMPLES, REJOIN_ODDS = 20, 1e-2
#: A third test, on each chip's drop summed over this many samples (chi-square, 3 x this
#: dof): a chip drifting off slowly (stuck under a slow load) is found at a third of the
#: disagreement one sample needs, before its error reaches 5 sigma of the wrench (one
#: sample's test lets through up to 0.64 sigma of wrench per unit of residual, 5.7 sigma
#: at its limit). Minkowski: |sum (noise + model)^2|^(1/2) <= |sum noise^2|^(1/2) +
#: sqrt(N) max|model|, so the odds hold. 10 samples: 0.1 s at 100 Hz.
SLOW_WINDOW = 10


@functools.lru_cache(maxsize=8)
def every_chip(n: int) -> np.ndarray:
    """``n`` chips all usable (read-only: shared by every cycle that has them all)."""
    every = np.ones(n, dtype=bool)
    every.setflags(write=False)
    return every


def _slow_limit(chips: int, load2: float) -> float:
    """The slow test's limit (whitened norm) on one chip's drop summed over the window, with
    ``chips`` in use at the load ``load2`` (`RedundancyCheck._load2`): its share of the odds
    (a quarter, split among the chips) plus the model's error over the window (Minkowski)."""
    return _slow_noise(chips) + math.sqrt(SLOW_WINDOW) * (
        CHIP_RESIDUAL_AT_REST + CHIP_RESIDUAL_AT_RANGE * load2
    )


@functools.lru_cache(maxsize=16)
def _slow_least(chips: int) -> float:
    """The square of `_slow_limit` at rest, its least: worked out once per number of chips."""
    return _slow_limit(chips, 0.0) ** 2


@functools.lru_cache(maxsize=16)
def _slow_noise(chips: int) -> float:
    """`_slow_limit`'s noise part, worked out once per number of chips."""
    return math.sqrt(chi2_quantile(3 * SLOW_WINDOW, CONSISTENCY_FALSE_ODDS / (4 * chips)))


@functools.lru_cache(maxsize=8)
def _every_key(n: int) -> bytes:
    """The slow test's key (`RedundancyCheck.slow_key`) of ``n`` chips all in use."""
    return every_chip(n).tobytes()


def _gradient_limit(dof: int, load2: float) -> float:
    """The gradient test's limit (whitened norm) at the load ``load2``: its half of the
    whole residual's odds plus the model's allowance."""
    return (
        math.sqrt(chi2_quantile(dof, CONSISTENCY_FALSE_ODDS / 4))
        + GRADIENT_RESIDUAL_AT_REST
        + GRADIENT_RESIDUAL_AT_RANGE * load2
    )


@functools.lru_cache(maxsize=64)
def _noise_limits(dof: int, chips: int, odds: float, gradient: bool) -> tuple[float, float]:
    """`RedundancyCheck._limits`' noise parts, worked out once per case."""
    # With a gradient estimated, its test takes half of the whole residual's odds.
    whole_odds = odds / (4 if gradient else 2)
    return math.sqrt(chi2_quantile(dof, whole_odds)), math.sqrt(chi2_quantile(3, odds / (4 * chips)))


def count_missing(usable: np.ndarray) -> int:
    """How many chips ``usable`` leaves out; none, without counting, when it is `every_chip`'s."""
    n = len(usable)
    return 0 if usable is every_chip(n) else n - int(np.count_nonzero(usable))


class RedundancyCheck:
    """Which of a sensor's chips agree with one deflection (`LinearModel.consistency`),
    sample by sample, and which were found out and stay out until they agree again."""

    def __init__(self) -> None:
        self.inconsistent = 0  # samples flagged
        self.suspects: dict[int, int] = {}  # chip index: samples it has agreed since found out
        # The slow test's window: each sample's drops (one list a sample, in turn) and load.
        self.slow_drops: list[list[float]] = [[] for _ in range(SLOW_WINDOW)]
        self.slow_loads = [0.0] * SLOW_WINDOW
        self.slow_tops = [0.0] * SLOW_WINDOW  # each sample's largest drop
        self.slow_count = 0  # samples in the window since it was last cleared
        self.slow_key = b""  # the chips the drops in the window were computed over
        # The usual sample's `FoldedCheck` and the versions it was folded at: the sensor's
        # (its zero and tare) and its temperature stage's (None: off). The channels' noise and
        # the calibration's loads are a pipeline's for its life.
        self._folded: tuple[tuple[int, int | None] | None, FoldedCheck | None] = (None, None)

    def usual(self, p: Checked, flux: np.ndarray, usable: np.ndarray) -> tuple[np.ndarray, bool] | None:
        """The usual sample in one product (`FoldedCheck`): with every chip usable and none
        found out, when every test passes, the linear wrench (N, Nm; before the temperature
        stage's stiffness) of ``flux`` as read (T) and whether it is extrapolated (beyond
        `EXTRAPOLATION_MARGIN` x the calibration's loads); None otherwise, having changed
        nothing: `chips` on the flux at the reference temperature then decides, as always."""
        n = len(usable)
        if usable is not every_chip(n) or self.suspects or p.sigma_t is None:
            return None
        f = self._fold(p)
        if f is None:
            return None
        y, sums = f.apply(flux)
        chi2, drops = sums[0], sums[1 : n + 1]
        load2 = max(sums[n + 2 : n + 8])
        whole, one = self._limits(p, load2, f.dof, n, CONSISTENCY_FALSE_ODDS)
        top = max(drops)  # a chip that cannot be left out drops 0, as `_agree`'s inf without it
        if not (chi2 <= whole**2 and top <= one**2):  # (NaN: not within; the general way says why)
            return None
        if f.gradient_dof and sums[n + 1] > _gradient_limit(f.gradient_dof, load2) ** 2:
            return None
        key = _every_key(n)
        if self._slow_find(drops, top, key, n, load2) is not None:
            return None
        self._slow_push(drops, top, key, load2)
        return y[f.wrench], max(sums[n + 8 :]) > 1.0

    def _fold(self, p: Checked) -> FoldedCheck | None:
        """The `FoldedCheck` of ``p``'s model, noise, temperature stage and tare, made anew when one changed."""
        thermal = p.thermal
        key = (p.version, None if thermal is None else thermal.version)
        kept, folded = self._folded
        if kept != key:
            scale, shift = (None, None) if thermal is None else (thermal.flux_scale, thermal.flux_shift)
            fitted = p.wrench_range
            # With no calibrated loads nothing is extrapolated: a bound no load reaches.
            bound = np.zeros(6) if fitted is None else 1.0 / (EXTRAPOLATION_MARGIN * fitted)
            folded = p.model.folded(
                p.sigma_t,  # type: ignore[arg-type]  # (not None: `usual` checked)
                scale,
                shift,
                p.tare_wrench,
                1.0 / (fitted if fitted is not None else SENSOR_RANGE),
                bound,
            )
            self._folded = (key, folded)
        return folded

    def chips(self, p: Checked, flux: np.ndarray, usable: np.ndarray) -> tuple[np.ndarray, int]:
        """The chips to estimate from, and `inconsistent` (+ `degraded`) when the usable
        chips' residual is beyond noise and model error: the chip whose leaving explains
        it is left out if the rest then agree, else the sample is flagged as it stands."""
        n_usable = len(usable) - count_missing(usable)
        if len(usable) - n_usable > p.max_missing_chips:
            return usable, 0  # too few chips for any estimate: the sample is invalid as it stands
        if p.model.H is None or p.sigma_t is None or n_usable * 3 <= p.model.unknowns:
            return usable, 0  # no flux model or no redundancy left: nothing to check against
        c = p.model.consistency(flux, p.sigma_t, usable)
        out, n_out = usable, n_usable
        if self.suspects:
            out = usable.copy()
            rejoin = self._limits(p, self._load2(p, c), c.dof, 1, REJOIN_ODDS)[1] ** 2
            for chip in list(self.suspects):
                if not usable[chip]:
                    continue  # missing or saturated this cycle: no news of it
                drop = c.chi2 - c.chi2_without[chip]
                self.suspects[chip] = self.suspects[chip] + 1 if drop <= rejoin else 0
                if self.suspects[chip] >= REJOIN_SAMPLES:
                    del self.suspects[chip]
                else:
                    out[chip] = False
            n_out = int(np.count_nonzero(out))
            if n_out < n_usable:
                if len(out) - n_out > p.max_missing_chips:
                    return usable, wire.FLAG_INCONSISTENT  # too many out to estimate without them
                c = p.model.consistency(flux, p.sigma_t, out)
        if not math.isfinite(c.chi2):
            return out, 0
        load2 = self._load2(p, c)
        culprit = None if self._agree(p, c, load2, n_out) else c.culprit()
        if culprit is None:
            culprit = self._slow_culprit(c, out, n_out, load2)
        if culprit is None:
            return out, 0 if n_out == n_usable else wire.FLAG_INCONSISTENT | wire.FLAG_DEGRADED
        self.inconsistent += 1
        rest = out.copy()
        rest[culprit] = False
        if (~rest).sum() <= p.max_missing_chips and np.isfinite(c.chi2_without[culprit]):
            again = p.model.consistency(flux, p.sigma_t, rest)
            if self._agree(p, again, self._load2(p, again), n_out - 1):
                self.suspects[culprit] = 0
                return rest, wire.FLAG_INCONSISTENT | wire.FLAG_DEGRADED
        return out, wire.FLAG_INCONSISTENT

    def _agree(self, p: Checked, c: Consistency, load2: float, chips: int) -> bool:
        """Both tests (and the gradient's, when estimated) within their limits. |noise + model|
        <= |noise| + |model|, so the false-alarm odds stay within CONSISTENCY_FALSE_ODDS."""
        whole, one = self._limits(p, load2, c.dof, chips, CONSISTENCY_FALSE_ODDS)
        if c.gradient_dof and c.gradient_chi2 > _gradient_limit(c.gradient_dof, load2) ** 2:
            return False
        # The largest drop is chi2 - the smallest chi2 without (inf for a chip not to be left
        # out); Python's min of 8 floats, not numpy's (a reduction costs 2 us).
        return c.chi2 <= whole**2 and c.chi2 - min(c.chi2_without.tolist()) <= one**2

    def _slow_culprit(self, c: Consistency, chips: np.ndarray, n: int, load2: float) -> int | None:
        """The chip whose drop summed over the last `SLOW_WINDOW` samples (over the same
        ``chips``, ``n`` of them) is beyond noise and model error, or None."""
        drops = c.drop.tolist()
        top, key = max(drops), chips.tobytes()
        culprit = self._slow_find(drops, top, key, n, load2)
        self._slow_push(drops, top, key, load2)
        if culprit is not None:
            self.slow_count = 0
        return culprit

    def _slow_find(self, drops: list[float], top: float, key: bytes, n: int, load2: float) -> int | None:
        """`_slow_culprit`'s answer with this sample's ``drops`` (``top`` their largest) in
        the window, the window left as it is."""
        count = self.slow_count + 1 if key == self.slow_key else 1
        if count < SLOW_WINDOW:
            return None
        turn = self.slow_count % SLOW_WINDOW
        # No chip's sum exceeds the sum of each sample's largest drop: under the least limit
        # (at rest) that settles the usual sample without summing the window per chip.
        if sum(self.slow_tops) - self.slow_tops[turn] + top <= _slow_least(n):
            return None
        rows = self.slow_drops[:turn] + [drops] + self.slow_drops[turn + 1 :]
        total = [sum(column) for column in zip(*rows)]
        loads = self.slow_loads[:turn] + [load2] + self.slow_loads[turn + 1 :]
        largest = max(total)
        return None if largest <= _slow_limit(n, max(loads)) ** 2 else total.index(largest)

    def _slow_push(self, drops: list[float], top: float, key: bytes, load2: float) -> None:
        """This sample into the slow test's window (a new set of chips starts it anew)."""
        if key != self.slow_key:
            self.slow_count, self.slow_key = 0, key
        turn = self.slow_count % SLOW_WINDOW
        self.slow_drops[turn], self.slow_loads[turn], self.slow_tops[turn] = drops, load2, top
        self.slow_count += 1

    def _load2(self, p: Checked, c: Consistency) -> float:
        """The load's square, as a fraction of the calibration's largest (largest over the axes)."""
        fitted = p.wrench_range
        # Python's max over 6 floats, not numpy's (a reduction costs 2 us).
        return (
            max(
                map(
                    abs,
                    ((c.wrench + p.tare_wrench) / (fitted if fitted is not None else SENSOR_RANGE)).tolist(),
                )
            )
            ** 2
        )

    def _limits(self, p: Checked, load2: float, dof: int, chips: int, odds: float) -> tuple[float, float]:
        """The limits (whitened norms) of the whole residual (``dof``) and of one chip's
        drop at the load ``load2`` (`_load2`): the noise's at ``odds`` (half to the whole,
        a quarter to one chip's, split among ``chips``; the last quarter is the slow
        test's) plus the model's own error at this load."""
        whole, one = _noise_limits(dof, chips, odds, p.model.gradient is not None)
        return (
            whole + MODEL_RESIDUAL_AT_REST + MODEL_RESIDUAL_AT_RANGE * load2,
            one + CHIP_RESIDUAL_AT_REST + CHIP_RESIDUAL_AT_RANGE * load2,
        )
