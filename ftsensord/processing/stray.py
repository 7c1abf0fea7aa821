"""A motor's field across the ring, learnt in the world as the tool turns.

A field's first-order gradient G (T/m; 3 x 3, symmetric and traceless: 5 numbers) adds
R_0i^T G p_i to chip i. Of its five parts the ring tells two from a load and a uniform field
(the in-plane ones: `model.geometry.separable_gradient`); the other three read exactly as
a load (docs/design/physics.md, "A motor's field"), so no estimator of one sample can take them
out. But a motor is fixed in the world, and so is its gradient G_w: the sensor sees
R^T G_w R (R = R_world,sensor), which mixes G_w's parts differently at each orientation.
The two parts the ring sees at each orientation, over a few orientations, give all five
of G_w; with it the three it cannot see are predicted and taken out of the flux, before
either estimator, and the consistency check no longer sees the two it can.

Each sample (unflagged, within the calibration's loads) gives y = Q^T (b - b_cal), the
in-plane gradient's two coefficients (Q: their flux directions, orthogonal to the load's
and the uniform field's, so no load moves y), and

    y = Q^T F T(R) g_w + c

with F the five gradient parts' flux (24 x 5, the drawn ring), T(R) taking G_w's five
numbers to the sensor's, and c what the zero has gained in those two directions since the
calibration (2 constants). [g_w, c] is estimated by recursive least squares with
forgetting (`MEMORY_SAMPLES`: a motor's current and the tool's place change). The flux is
corrected by F (T(R_tare) g_w,tare - T(R) g_w): the tare's zero kept the gradient of its
time, so what is taken out is the change since. A gradient at the tare is known if the
tool had turned before it; else it is the one learnt since, when that explains the tare's
y better than none does (a motor on throughout), or the least one that gives the tare's y
(none, a motor switched on after the tare).

Needs the tool's orientation (the orientation stream, `processing.gravity`). Until the turns
seen determine g_w well enough (`CORRECT_WITHIN`), nothing is corrected, and a sample whose
in-plane gradient changed beyond noise since the tare is flagged `inconsistent`: its hidden
parts may carry a false load of the same order.
"""

from __future__ import annotations

from collections import deque
from typing import Any, ClassVar

import numpy as np

from ftsensord.model.consistency import chi2_quantile
from ftsensord.model.geometry import GRADIENT_PARTS, SensorGeometry, gradient_basis, separable_gradient
from ftsensord.model.linear import LinearModel

#: Samples the estimate remembers (the weight of older ones falls by e over this many): 30 s
#: at 100 Hz. A motor's current and the tool's place change over seconds; a hand turning the
#: tool visits the few orientations the estimate needs within them.
MEMORY_SAMPLES = 3000
#: The correction starts when the false wrench it takes out is known to within this (1 sigma,
#: N and Nm, from the estimate's covariance: the noise's part): a quarter of the aim near a motor
#: (0.05 N, 2 mNm), so that its own error adds 3 % to an error at the figure in quadrature.
CORRECT_WITHIN = np.array([0.0125, 0.0125, 0.0125, 0.5e-3, 0.5e-3, 0.5e-3])
#: Before that, an in-plane gradient changed since the tare raises an alarm that flags every
#: sample until the gradient is learnt (or the next tare): at some orientations the in-plane
#: parts are small while the hidden ones are large, so a sample's own in-plane part cannot
#: tell which samples are right. The change counts when, in the mean of the last
#: `CHANGE_SAMPLES` samples, it is beyond noise at `CHANGE_ODDS` (chi-square, 2 dof: 5.3
#: sigma) and a gradient of its size, its hidden parts as large as at a random orientation,
#: would make a false wrench beyond `ALARM_WRENCH` (N, Nm), 1.5 times that aim: at
#: the figure itself a 2 A m^2 motor at 25 cm, whose false wrench is within it (1.3 mNm RMS
#: uncorrected), raised it on two parts of three for the 7 s learning took; at 1.5 times it
#: rises at 15 cm (8.7 mNm), not at 25 (benchmarks/accuracy/motor.py; docs/results/accuracy.md).
CHANGE_ODDS = 1e-6
CHANGE_SAMPLES = 10
#: A tare whose in-plane reading is further than this from the calibration's (T) was taken in
#: a gradient: then a turn, or any change beyond noise, raises the alarm until the gradient
#: is learnt, since the first turn can move the hidden parts far more than the in-plane ones
#: (30 mNm against 5 uT in tests/test_world_gradient.py). Without a motor the
#: zero's own in-plane offset stayed within 0.4 uT (parts 11-13, 1.0 s tares); 2 uT is about
#: 0.25 uT/mm across the ring, a 2 A m^2 motor within some 25 cm.
TARE_GRADIENT_T = 2e-6
ALARM_WRENCH = 1.5 * np.array([0.05, 0.05, 0.05, 2e-3, 2e-3, 2e-3])
#: The covariance of the five parts of a random traceless symmetric gradient (isotropic:
#: the traceless part of (A + A^T) / 2, A's entries N(0, 1)): diagonal parts 2/3 and -1/3
#: between them, off-diagonal parts 1/2.
_ISOTROPIC = np.array(
    [
        [2 / 3, -1 / 3, 0, 0, 0],
        [-1 / 3, 2 / 3, 0, 0, 0],
        [0, 0, 0.5, 0, 0],
        [0, 0, 0, 0.5, 0],
        [0, 0, 0, 0, 0.5],
    ]
)
#: The estimate is solved again every this many samples learnt (0.1 s at 100 Hz): it moves
#: slowly (a 30 s memory), and a 7 x 7 inverse each sample would double the stage's cost.
SOLVE_EVERY = 10
#: Learnt only while the tool turns slower than this (rad a sample; 0.5 rad/s at 100 Hz): the
#: orientation and the chips' conversions are milliseconds apart, and 10 ms at 0.5 rad/s
#: turns a motor's 60 uT by 0.3 uT, a tenth of y's noise; a fast turn would teach a bias.
STEADY_RAD = 0.005
_STEADY_TRACE = 1.0 + 2.0 * float(np.cos(STEADY_RAD))  # tr(A^T B) of two rotations STEADY_RAD apart


def parts(G: np.ndarray) -> np.ndarray:
    """The five numbers of a traceless symmetric G in the basis of `gradient_basis` (..., 5)."""
    return np.stack([G[..., i, j] for i, j in GRADIENT_PARTS], axis=-1)


_BASIS = gradient_basis()
_PART_INDEX = [3 * i + j for i, j in GRADIENT_PARTS]  # each part's place in a flattened 3 x 3


def turned(R: np.ndarray) -> np.ndarray:
    """T(R) (5 x 5): the parts of R^T G R from G's, for a sensor turned by R = R_world,sensor."""
    return (R.T @ _BASIS @ R).reshape(5, 9)[:, _PART_INDEX].T


class WorldGradient:
    """One sensor's learnt world gradient (module docstring): each sample, `turn_to` its
    orientation, `apply` to correct its flux, `learn` from it when it may; `tared` when the
    pipeline takes its zero."""

    def __init__(self, model: LinearModel, sigma_t: np.ndarray, geometry: SensorGeometry | None = None):
        if model.H is None:
            raise ValueError("the world gradient needs the calibration's flux model H")
        ring = geometry or SensorGeometry.ring()
        self.zero = model.zero.copy()  # the calibration's own zero: y is measured from it
        self.F = ring.gradient_flux()
        self.Q = separable_gradient(model.H, model.room, ring.gradient_directions())
        self.QF = self.Q.T @ self.F
        self.KA = model.KA
        self.sigma_y = float(np.sqrt(np.mean(sigma_t**2)))  # Q's columns are unit: y's noise per part
        self.limit = chi2_quantile(self.Q.shape[1], CHANGE_ODDS)
        # The false wrench per unit of in-plane change, for a gradient turned at random (N/T, Nm/T).
        seen = np.trace(self.QF @ _ISOTROPIC @ self.QF.T)
        self.false_per_change = np.sqrt(np.diag(self.KA @ self.F @ _ISOTROPIC @ self.F.T @ self.KA.T) / seen)
        self.forget = 1.0 - 1.0 / MEMORY_SAMPLES
        self.forget_all()

    name: ClassVar[str] = "stray"

    def forget_all(self) -> None:
        """Forget everything: what was learnt and the tare."""
        self.forget_learnt()
        self.R: np.ndarray | None = None  # this sample's orientation
        self.T: np.ndarray | None = None  # and its T(R)
        self.steady = False  # it turned little since the sample before
        self.tare_T: np.ndarray | None = None  # T(R) at the tare
        self.tare_y: np.ndarray | None = None
        self.tare_g: np.ndarray | None = None  # g_w at the tare; None until known
        self.recent: deque[np.ndarray] = deque(maxlen=CHANGE_SAMPLES)  # y's departures from what is expected
        self.recent_sum = np.zeros(self.Q.shape[1])
        self.alarm = False  # a change since the tare, not yet learnt
        self.tare_in_gradient = False  # the tare's in-plane reading says a gradient was there

    def _clear_recent(self) -> None:
        self.recent.clear()
        self.recent_sum = np.zeros(self.Q.shape[1])

    def forget_learnt(self) -> None:
        """Start learning afresh: the gradient changed (a motor switched on or its current
        changed), so what was learnt before describes another field."""
        k = self.Q.shape[1]
        self.info = np.zeros((5 + k, 5 + k))  # sum of M^T M / sigma^2, forgotten geometrically
        self.moment = np.zeros(5 + k)
        self.theta: np.ndarray | None = None  # [g_w (T/m), c (T)] once it determines the correction
        self.samples = 0

    def turn_to(self, R: np.ndarray | None) -> None:
        """This sample's orientation, R_world,sensor (None: unknown: nothing is corrected)."""
        # tr(A^T B) = 1 + 2 cos(angle between A and B): compared without the arccos.
        self.steady = R is not None and self.R is not None and float(np.vdot(self.R, R)) >= _STEADY_TRACE
        self.R = R
        self.T = None if R is None else turned(R)  # used up to three times a sample
        if not self.steady:
            self._clear_recent()  # a turn: the change is judged afresh at the new orientation, from its first sample
            if self.tare_in_gradient and self.theta is None and R is not None:
                self.alarm = True  # tared in a gradient not yet learnt: a turn moves its hidden parts

    def learn(self, flux: np.ndarray) -> None:
        """Learn from this sample's flux (T, the stage's input): the caller says it may (every
        chip read and unflagged, the load within the calibration's); only while steady."""
        if self.T is None or not self.steady:
            return
        y = self.Q.T @ (flux - self.zero)
        M = np.hstack([self.QF @ self.T, np.eye(self.Q.shape[1])]) / self.sigma_y
        self.info = self.forget * self.info + M.T @ M
        self.moment = self.forget * self.moment + M.T @ (y / self.sigma_y)
        self.samples += 1
        if self.samples % SOLVE_EVERY == 0:
            self._solve()

    def _solve(self) -> None:
        try:
            cov = np.linalg.inv(self.info)
        except np.linalg.LinAlgError:
            return  # too few orientations yet: singular
        assert self.T is not None
        J = self.KA @ self.F @ self.T  # the false wrench per unit g_w at this orientation
        variance = np.sum((J @ cov[:5, :5]) * J, axis=1)
        # A negative or non-finite variance is round-off of a nearly singular matrix: the
        # orientations seen do not determine g_w yet.
        if np.all(np.isfinite(variance)) and np.all(variance >= 0) and np.all(variance <= CORRECT_WITHIN**2):
            if self.theta is None:
                self._clear_recent()  # y is compared with the learnt field's from now on, not the tare's
            self.theta = cov @ self.moment
            if self.tare_g is None and self.tare_y is not None and self.tare_T is not None:
                # The gradient at the tare, from its y: the field learnt now, if that explains
                # the tare's y better than no field does (a motor on throughout); else the
                # least gradient that gives it (none, a motor switched on after the tare).
                g, c = self.theta[:5], self.theta[5:]
                same, off = self.tare_y - self.QF @ self.tare_T @ g - c, self.tare_y - c
                self.tare_g = (
                    g.copy() if same @ same < off @ off else np.linalg.pinv(self.QF @ self.tare_T) @ off
                )

    def tared(self, zero: np.ndarray) -> np.ndarray:
        """The pipeline took ``zero`` (T, the stage's input) as its zero at the newest
        orientation; the zero goes on as it is (the gradient's change is measured from it)."""
        self.tare_T = self.T
        self.tare_y = self.Q.T @ (zero - self.zero)
        self.tare_in_gradient = float(np.sqrt(self.tare_y @ self.tare_y)) > TARE_GRADIENT_T
        self.tare_g = None if self.theta is None else self.theta[:5].copy()
        self._clear_recent()
        self.alarm = False
        return zero

    def configure(self, rate_hz: float) -> None:
        pass  # counted in samples, each learnt at its own orientation

    def gap(self, periods: int) -> None:
        pass  # the gradient is fixed in the world: a pause changes nothing of it

    def restart(self) -> None:
        pass  # it learns from the flux, whatever estimator reads it

    @property
    def correcting(self) -> bool:
        return (
            self.theta is not None
            and self.tare_g is not None
            and self.tare_T is not None
            and self.T is not None
        )

    def apply(self, flux: np.ndarray) -> tuple[np.ndarray, bool]:
        """The flux with the learnt gradient's change since the tare taken out, and whether
        the sample is to be flagged (a gradient changed since the tare, not yet learnt)."""
        T = self.T
        if self.tare_y is None or T is None:
            return flux, self.alarm  # untared, or turned we know not how: nothing to compare or correct
        # What y should be: the learnt field's at this orientation, else the tare's (no change).
        expected = self.QF @ T @ self.theta[:5] + self.theta[5:] if self.theta is not None else self.tare_y
        if len(self.recent) == self.recent.maxlen:
            self.recent_sum -= self.recent[0]
        self.recent.append(self.Q.T @ (flux - self.zero) - expected)
        self.recent_sum += self.recent[-1]
        mean = self.recent_sum / len(self.recent)
        size = float(np.sqrt(mean @ mean))
        threat = size**2 * len(self.recent) / self.sigma_y**2 > self.limit and (
            self.tare_in_gradient
            and self.theta is None
            or bool(np.any(size * self.false_per_change > ALARM_WRENCH))
        )
        # A change raises the alarm once: learning starts afresh from it (samples from
        # before would bias what is learnt next), and the alarm stays until it is learnt.
        if threat and (self.theta is not None or not self.alarm):
            self.forget_learnt()
            self._clear_recent()
            self.alarm = True
        if not self.correcting:
            return flux, self.alarm
        assert self.theta is not None and self.tare_g is not None and self.tare_T is not None
        self.alarm = False
        return flux - self.F @ (T @ self.theta[:5] - self.tare_T @ self.tare_g), False

    def status(self) -> dict[str, Any]:
        g = None if self.theta is None else self.theta[:5]
        return {
            "samples": self.samples,
            "correcting": self.correcting,
            "alarm": self.alarm,
            "gradient_ut_per_mm": None if g is None else round(float(np.linalg.norm(g)) * 1e3, 4),
        }
