"""The redundancy check's numbers: how well a sensor's chips agree with one deflection.

`ConsistencyMaps` folds the weighted least-squares fit of the forward model b - b0 = H xi
over one set of chips into one matrix, so that a sample's check (`Consistency`: the
whitened residual, each chip's share of it, the fitted wrench) costs one product;
`FoldedCheck` goes one step further for the usual sample (every chip in use): the
temperature stage's affine map and the model's K A folded in too, so the check and the
linear wrench are one product. `chi2_quantile` gives the tests' limits.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np


class ConsistencyMaps:
    """`LinearModel.consistency`'s sums for one set of chips and channel noise, folded into
    one matrix at build so that a sample costs one (2 |S| + 6) x |S| product.

    With A = W_S H_S (whitened, room columns included), the residual is r = P x with the
    projector P = I - A pinv(A), x = W_S (b_S - b0_S), and leaving chip c (channels c) out
    lowers |r|^2 by r_c^T (P_cc)^-1 r_c (the deletion identity of least squares, exact when
    the rest still see every column of A: P_cc is then invertible). So the rows are P,
    K pinv(A)[:6] (the wrench) and G P, G block-diagonal of the (P_cc)^-1; the whitening
    1/sigma is folded into the columns.

    The last ``gradient`` columns of H, when any, are a field's gradient g: the rows L with
    |L x|^2 = g_hat^T Cov(g_hat)^-1 g_hat (chi-square, ``gradient`` dof, under noise alone)
    follow, L = C^T pinv(A)[-k:] with C C^T = Cov^-1 (Cholesky), Cov = (A^T A)^-1's block.
    """

    def __init__(self, H: np.ndarray, K: np.ndarray, sigma: np.ndarray, chips: np.ndarray, gradient: int = 0):
        n_chips, unknowns = len(chips), H.shape[1]
        self.channels = np.repeat(chips, 3)
        self.all = bool(chips.all())
        self.used = np.flatnonzero(chips)
        self.dof = 3 * len(self.used) - unknowns
        self.dof_without = self.dof - 3
        self.n = 3 * len(self.used)
        self.gradient_dof = gradient
        self.none_left = np.full(n_chips, np.inf)
        A = H[self.channels] / sigma[self.channels, None]
        self.maps: np.ndarray | None = None
        self.chip_rows: np.ndarray | None = None  # `FoldedCheck`'s: each chip's drop as a square
        if self.dof <= 0 or np.linalg.matrix_rank(A) < unknowns:
            return  # too few chips, or they do not see every axis: nothing to test
        pinv = np.linalg.pinv(A)
        P = np.eye(self.n) - A @ pinv
        G = np.zeros((self.n, self.n))
        Ct = np.zeros((self.n, self.n))  # per chip C^T with C C^T = (P_cc)^-1: |C^T r_c|^2 is its drop
        can_leave = np.zeros(len(self.used), dtype=bool)
        for k in range(len(self.used)):
            part = slice(3 * k, 3 * k + 3)
            rest = np.ones(self.n, dtype=bool)
            rest[part] = False
            # The same rank test the chips as a whole pass: the rest must still see every column.
            if self.dof_without > 0 and np.linalg.matrix_rank(A[rest]) == unknowns:
                G[part, part] = np.linalg.inv(P[part, part])
                # P_cc is a principal block of a projector, invertible here: positive definite.
                Ct[part, part] = np.linalg.cholesky(G[part, part]).T
                can_leave[k] = True
        self.stays = np.ones(n_chips, dtype=bool)  # not in use, or the rest would not see every column
        self.stays[self.used[can_leave]] = False
        self.any_stays = bool(self.stays.any())
        rows = [P, K @ pinv[:6], G @ P]
        if gradient:
            cov = np.linalg.inv(A.T @ A)[-gradient:, -gradient:]
            rows.append(np.linalg.cholesky(np.linalg.inv(cov)).T @ pinv[-gradient:])
        self.maps = np.vstack(rows) / sigma[self.channels]
        self.chip_rows = (Ct @ P) / sigma[self.channels]
        # Sums each chip's 3 channels in one product: a reduction along an axis costs 5 us.
        self.per_chip = np.kron(np.eye(len(self.used)), np.ones((3, 1)))

    def apply(self, d: np.ndarray) -> Consistency:
        """The check of one sample from its flux minus the zero ``d`` (T, every channel)."""
        if self.maps is None:
            return Consistency(
                np.inf,
                self.dof,
                np.full(6, np.nan),
                self.none_left.copy(),
                self.dof_without,
                np.zeros(len(self.none_left)),
            )
        n = self.n
        y = self.maps @ (d if self.all else d[self.channels])
        r = y[:n]
        chi2 = float(r @ r)
        # G's rows are 0 for a chip that cannot be left out: its drop is 0.
        drops = (r * y[n + 6 : 2 * n + 6]) @ self.per_chip
        g = y[2 * n + 6 :]
        if self.all:
            drop = drops
        else:
            drop = np.zeros(len(self.none_left))
            drop[self.used] = drops
        without = chi2 - drop
        if self.any_stays:
            without[self.stays] = np.inf
        return Consistency(
            chi2,
            self.dof,
            y[n : n + 6],
            without,
            self.dof_without,
            drop,
            float(g @ g) if self.gradient_dof else 0.0,
            self.gradient_dof,
        )


@dataclass(slots=True)  # not frozen: a frozen dataclass's __init__ costs a microsecond a sample
class Consistency:
    """What the redundancy check found in one sample (`LinearModel.consistency`).

    ``chi2``: the squared whitened residual over the chips used, ``dof`` its degrees
    of freedom; ``wrench`` K xi_hat (N, Nm) from the same weighted fit; ``chi2_without``
    (one per chip): the same with that chip left out (inf for a chip not in use or
    when the rest do not see all six axes), ``dof_without`` its degrees of freedom;
    ``drop`` (one per chip) chi2 minus chi2_without, 0 where the chip cannot be left out.
    ``gradient_chi2``: the estimated gradient's squared whitened size (chi-square with
    ``gradient_dof`` under noise alone; 0 with no gradient estimated).
    """

    chi2: float
    dof: int
    wrench: np.ndarray
    chi2_without: np.ndarray
    dof_without: int
    drop: np.ndarray
    gradient_chi2: float = 0.0
    gradient_dof: int = 0

    def culprit(self) -> int:
        """The chip whose leaving lowers the residual most (its index in the sensor)."""
        return int(np.argmin(self.chi2_without))


@functools.lru_cache(maxsize=64)
def chi2_quantile(dof: int, odds: float) -> float:
    """The x with P(chi-square(dof) > x) = ``odds``: exact survival function for an
    integer dof (the Poisson sum, with erfc for an odd dof), inverted by bisection."""
    if dof < 1 or not 0 < odds < 1:
        raise ValueError(f"need dof >= 1 and 0 < odds < 1, got {dof}, {odds}")

    def survival(x: float) -> float:
        h = x / 2
        if dof % 2 == 0:
            term = total = math.exp(-h)
            for i in range(1, dof // 2):
                term *= h / i
                total += term
            return total
        total = math.erfc(math.sqrt(h))
        term = math.sqrt(2 * x / math.pi) * math.exp(-h)
        for i in range(1, (dof + 1) // 2):
            total += term
            term *= x / (2 * i + 1)
        return total

    lo, hi = 0.0, float(dof)
    while survival(hi) > odds:
        hi *= 2
    for _ in range(200):  # to round-off: 200 halvings of any bracket below 2^60
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if survival(mid) > odds else (lo, mid)
    return hi


class FoldedCheck:
    """The usual sample's check and linear wrench in one product, then one more for the
    tests' squares: every chip in use, the flux as read (T), ``b``, brought to the reference
    temperature by the temperature stage's b_ref = b scale - shift before anything else.

    y = M b + c stacks, over d = b_ref - b0: the whitened residual r (`ConsistencyMaps`'
    P), each chip's C^T r_c (its drop is the square: `ConsistencyMaps.chip_rows`), the
    gradient's L x, the model's wrench K A d (N, Nm), then two loads as fractions, squared
    below: the fitted wrench's (K pinv(A)[:6] x + ``load_offset``) * ``load_scale`` and
    the model's (K A d + ``load_offset``) * ``bound_scale``. `apply` returns y and, from
    its squares in one product, [|r|^2, each chip's drop, |L x|^2, the load's six squares,
    the bound's six]. Only the constant part moves into ``c``: its cancellation costs
    1e-12 of a whitened residual of 1 (the flux's size over its noise times round-off).
    """

    def __init__(
        self,
        maps: ConsistencyMaps,
        KA: np.ndarray,
        zero: np.ndarray,
        scale: np.ndarray | None,
        shift: np.ndarray | None,
        load_offset: np.ndarray,
        load_scale: np.ndarray,
        bound_scale: np.ndarray,
    ):
        if not maps.all or maps.maps is None or maps.chip_rows is None:
            raise ValueError("a folded check needs every chip in use and redundancy to check")
        n, k = maps.n, maps.gradient_dof
        self.chips, self.dof, self.gradient_dof = n // 3, maps.dof, k
        m = maps.maps
        self.wrench = slice(2 * n + k, 2 * n + k + 6)
        rows = np.vstack(
            [
                m[:n],
                maps.chip_rows,
                m[2 * n + 6 :],
                KA,
                m[n : n + 6] * load_scale[:, None],
                KA * bound_scale[:, None],
            ]
        )
        offset = zero if shift is None else zero + shift  # b_ref - b0 = b scale - (shift + b0)
        self.c = -(rows @ offset)
        self.c[-12:] += np.concatenate([load_offset * load_scale, load_offset * bound_scale])
        self.M = rows if scale is None else rows * scale[None, :]
        # The squares' sums: |r|^2, one column a chip, |L x|^2, then the twelve squares as they are.
        sums = np.zeros((len(rows), 2 + self.chips + 12))
        sums[:n, 0] = 1.0
        sums[n + np.arange(n), 1 + np.arange(n) // 3] = 1.0
        sums[2 * n : 2 * n + k, 1 + self.chips] = 1.0
        sums[-12:, 2 + self.chips :] = np.eye(12)
        self.sums = sums

    def apply(self, b: np.ndarray) -> tuple[np.ndarray, list[float]]:
        """y (see the class) for flux ``b`` as read (T, every channel), and its squares' sums."""
        y = self.M @ b
        y += self.c
        return y, ((y * y) @ self.sums).tolist()
