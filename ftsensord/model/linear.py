"""The paper's force model (sections IV and V).

Flux b_i (T, chip frame {S_i}) -> magnet position p_i = M_i b_i + o_i (eq. 1,
m, chip frame) -> magnet positions in the centre frame {C} -> centre-piece
pose T_0C by registration against the magnets' fixed positions in {0} ->
deflection twist xi = log(T_0C)^vee (m, rad). At run time the calibrated
linear map does it all at once: w = K A (b - b0), w = [f; m] in N, Nm in
frame {0}.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np

from ftsensord.model import se3
from ftsensord.model.consistency import Consistency, ConsistencyMaps, FoldedCheck
from ftsensord.model.geometry import SensorGeometry, separable_gradient
from ftsensord.model.registration import Registration, register

#: The sensor's range (paper): +-50 N in X and Y, +-20 N in Z, +-0.2 Nm, frame {0}.
SENSOR_RANGE = np.array([50.0, 50.0, 20.0, 0.2, 0.2, 0.2])
#: A linear estimate is flagged `extrapolated` past this multiple of the calibration's
#: largest load on an axis: up to 1.5x no axis's error relative to the load has grown
#: 1.5-fold, by 3x one has nearly tripled (benchmarks/accuracy/extrapolation.py, docs/guide/calibration.md).
EXTRAPOLATION_MARGIN = 1.5


@dataclass(frozen=True)
class PositionMap:
    """p = M b + o per chip (eq. 1): ``M`` (n, 3, 3) in m/T, ``o`` (n, 3) in m."""

    M: np.ndarray
    o: np.ndarray

    def positions(self, b: np.ndarray) -> np.ndarray:
        """Magnet positions (n, 3; m, chip frames) from flux ``b`` (n, 3; T, chip frames)."""
        return np.einsum("nij,nj->ni", self.M, b) + self.o


def fit_position_map(b: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares (M, o) with p ~ M b + o, from k >= 4 samples of flux ``b``
    (k, 3; T) and magnet position ``p`` (k, 3; m), as the paper's stage experiment."""
    b, p = np.asarray(b, dtype=float), np.asarray(p, dtype=float)
    if b.shape != p.shape or b.ndim != 2 or b.shape[1] != 3:
        raise ValueError(f"flux and positions must both be k x 3, got {b.shape} and {p.shape}")
    centred = b - b.mean(axis=0)
    # Rank tests relative to the largest spread: an axis that varies less than 1e-9 of
    # the others is round-off, and its slope would be noise. The positions first: a
    # recorded sweep along fewer axes still has noisy flux of rank 3, fitted to noise.
    sp = np.linalg.svd(p - p.mean(axis=0), compute_uv=False) if len(p) else np.zeros(1)
    if len(b) < 4 or sp[0] == 0 or sp[-1] < 1e-9 * sp[0]:
        raise ValueError("the sweep must move the magnet along all three axes (position rank < 3)")
    s = np.linalg.svd(centred, compute_uv=False)
    if s[0] == 0 or s[-1] < 1e-9 * s[0]:
        raise ValueError("the sweep must move the magnet along all three axes (flux rank < 3)")
    Mt, *_ = np.linalg.lstsq(centred, p - p.mean(axis=0), rcond=None)
    M = Mt.T
    return M, p.mean(axis=0) - M @ b.mean(axis=0)


def centre_pose(
    b: np.ndarray, geometry: SensorGeometry, position_map: PositionMap, weights: np.ndarray | None = None
) -> Registration:
    """Pose T_0C of the centre piece from the chips' flux ``b`` (n, 3; T).

    Loop closure (eq. 5): 0p_mi = 0p_C + R_0C Cp_mi with Cp_mi = Cp_si + R_CSi Sip_mi;
    the centre frame equals {0} at rest, so the nominal chip poses give Cp_si, R_CSi.
    ``weights`` (n,) drop or down-weight chips (0 for a missing one).
    """
    in_chip = position_map.positions(b)
    in_centre = geometry.chip_p + np.einsum("nij,nj->ni", geometry.chip_R, in_chip)
    return register(in_centre, geometry.magnet_p, weights)


def deflection_twist(
    b: np.ndarray, geometry: SensorGeometry, position_map: PositionMap, weights: np.ndarray | None = None
) -> np.ndarray:
    """The deflection twist xi = log(T_0C)^vee = [v; w] (m, rad)."""
    return se3.log_se3(centre_pose(b, geometry, position_map, weights).as_pose())


@dataclass
class LinearModel:
    """w = K A (b - b0): ``K`` (6, 6) stiffness (N/m, Nm/rad), ``A`` (6, 24)
    flux-to-twist map (m/T, rad/T), ``zero`` b0 (24,) the flux at no load (T).

    ``b`` stacks the 8 chips' flux [b_1; ...; b_8], each in its chip frame.

    ``room`` (24, 3; orthonormal columns), when set, are the flux directions a
    uniform field (the Earth's, fixed in the world) takes in this sensor's chips:
    they are projected out of b - b0 before K A, w = K A P (b - b0) with
    P = I - room room^T, so that turning the sensor in a uniform field gives no
    wrench. (A fitted with those directions projected out already has A room = 0,
    and P changes nothing; for one fitted without, it costs the part of the load's
    signal along them.)

    ``gradient`` (24 x k, orthonormal, orthogonal to H and room; `with_gradient`), when
    set, are the directions of a field's gradient across the ring that the chips tell
    from a load: projected out of K A as well, and estimated in `consistency`, whose
    `Consistency.gradient_chi2` tells a nearby source (a motor) from noise.
    """

    K: np.ndarray
    A: np.ndarray
    zero: np.ndarray
    H: np.ndarray | None = None
    room: np.ndarray | None = None
    gradient: np.ndarray | None = None
    KA: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        # KA is what runs every cycle: one 6 x 24 product, computed once, projection included.
        self.KA = self.K @ self.A
        if self.room is not None:
            self.room = np.asarray(self.room, dtype=float)
            n = self.A.shape[1]
            # 1e-9: orthonormal to round-off; anything worse is not a set of directions.
            if (
                self.room.ndim != 2
                or self.room.shape[0] != n
                or self.room.shape[1] >= n
                or not np.allclose(self.room.T @ self.room, np.eye(self.room.shape[1]), atol=1e-9)
            ):
                raise ValueError(
                    f"room must be {n} x k with orthonormal columns, got shape {self.room.shape}"
                )
            self.KA = self.KA - (self.KA @ self.room) @ self.room.T
        if self.gradient is not None:
            self.gradient = np.asarray(self.gradient, dtype=float)
            n = self.A.shape[1]
            # 1e-9: orthonormal, and orthogonal to the room's directions, to round-off: the two
            # projections then make one.
            if (
                self.gradient.ndim != 2
                or self.gradient.shape[0] != n
                or not np.allclose(self.gradient.T @ self.gradient, np.eye(self.gradient.shape[1]), atol=1e-9)
                or (self.room is not None and not np.allclose(self.room.T @ self.gradient, 0.0, atol=1e-9))
            ):
                raise ValueError(
                    f"gradient must be {n} x k with orthonormal columns orthogonal to room's, "
                    f"got shape {self.gradient.shape}"
                )
            self.KA = self.KA - (self.KA @ self.gradient) @ self.gradient.T
        # How many unknowns the columns fit (`unknowns`): asked every sample, fixed at build.
        self._unknowns = 6 + sum(c.shape[1] for c in (self.room, self.gradient) if c is not None)
        self._last_check: tuple[np.ndarray, np.ndarray, ConsistencyMaps] | None = None
        self._with_gradient: LinearModel | None = None
        self._subsets: dict[bytes, np.ndarray] = {}  # degraded maps, by the chips left
        self._checks: dict[bytes, ConsistencyMaps] = {}  # consistency maps, by chips and noise

    def twist(self, b: np.ndarray) -> np.ndarray:
        return self.A @ (b - self.zero)

    def wrench(self, b: np.ndarray) -> np.ndarray:
        """[f; m] in N, Nm, frame {0}, from stacked flux ``b`` (24,) or (n, 24) in T."""
        return (b - self.zero) @ self.KA.T

    def with_zero(self, zero: np.ndarray) -> LinearModel:
        """The same model tared to a new no-load flux."""
        tared = LinearModel(self.K, self.A, np.asarray(zero, dtype=float), self.H, self.room, self.gradient)
        # Its maps do not depend on the zero: no 1.4 ms after a tare.
        tared._subsets, tared._checks = self._subsets, self._checks
        return tared

    def rejecting_room_field(
        self, room: np.ndarray | None = None, geometry: SensorGeometry | None = None
    ) -> LinearModel:
        """The same model blind to a uniform field: along ``room`` (24 x k,
        orthonormal; e.g. measured at calibration), or the directions ``geometry``'s
        chip orientations give (default the nominal ring's), exact for a sensor built
        as drawn and leaking, for an as-built one, in proportion to its chips' tilts."""
        if room is None:
            room = (geometry or SensorGeometry.ring()).room_directions()
        return LinearModel(self.K, self.A, self.zero, self.H, room)

    def with_gradient(self) -> LinearModel:
        """The same model blind also to a field's first-order gradient across the ring, as
        far as the chips tell it from a load (`separable_gradient` of the drawn ring's
        `SensorGeometry.gradient_directions`: the two in-plane parts); the rest of a
        gradient reads as a load, and no estimator can tell it from one. Made once (its
        maps with it); a model that has it is its own. Needs H."""
        if self.gradient is not None:
            return self
        if self._with_gradient is None:
            if self.H is None:
                raise ValueError("this calibration has no flux model H: no gradient to tell from a load")
            gradient = separable_gradient(self.H, self.room, SensorGeometry.ring().gradient_directions())
            self._with_gradient = LinearModel(self.K, self.A, self.zero, self.H, self.room, gradient)
        return self._with_gradient

    @property
    def columns(self) -> np.ndarray:
        """The forward model's columns, b - b0 = H xi + room u + gradient g: what the
        degraded estimate and the consistency check fit (24 x `unknowns`). Needs H."""
        if self.H is None:
            raise ValueError("this calibration has no flux model H")
        return np.hstack([c for c in (self.H, self.room, self.gradient) if c is not None])

    @property
    def unknowns(self) -> int:
        """How many unknowns those columns are: 6 of the deflection, and the room's and
        the gradient's when set."""
        return self._unknowns

    def wrench_from(self, b: np.ndarray, chips: np.ndarray) -> np.ndarray:
        """The wrench from the chips where ``chips`` (bool, one per chip) is true only.

        Degraded mode: the calibration's forward model ``b - b0 = H xi`` (H fitted
        on the calibration data) gives the twist by least squares on the channels
        left, xi = pinv(H_S) (b_S - b0_S), and w = K xi. Needs H, and the chips
        left must still see all six axes (rank 6). With ``room`` set, the uniform
        field u is estimated beside the twist, b - b0 = H xi + room u, which needs
        the chips left to tell the two apart (rank 6 + 3); with ``gradient`` too, its
        part g as well.
        """
        channels = np.repeat(np.asarray(chips, dtype=bool), 3)
        return self.map_from(chips) @ (b[channels] - self.zero[channels])

    def map_from(self, chips: np.ndarray) -> np.ndarray:
        """`wrench_from`'s map, K pinv(H_S) (6 x the channels of ``chips``), built once;
        ValueError without H or when the chips left do not see all six axes."""
        if self.H is None:
            raise ValueError("this calibration has no flux model H: no estimate from fewer chips")
        channels = np.repeat(np.asarray(chips, dtype=bool), 3)
        key = channels.tobytes()
        M = self._subsets.get(key)
        if M is None:
            H_S = self.columns[channels]
            if np.linalg.matrix_rank(H_S) < H_S.shape[1]:
                raise ValueError(
                    "the chips left do not see all six axes"
                    + ("" if H_S.shape[1] == 6 else " apart from the room's field")
                )
            M = self._subsets[key] = self.K @ np.linalg.pinv(H_S)[:6]
        return M

    def build_maps(self, sigma: np.ndarray, max_missing: int) -> None:
        """Build now every map `wrench_from` and `consistency` (channel noise ``sigma``, T)
        can be asked for: the chips left after up to ``max_missing`` losses (37 for 8 chips
        and 2, 13 ms). A cycle at a fault then builds none (about 1 ms each), and their
        memory (about 0.4 MB) is taken at start, not over hours of faults. Needs H."""
        chips = self.A.shape[1] // 3
        for k in range(max_missing + 1):
            for lost in itertools.combinations(range(chips), k):
                left = np.ones(chips, dtype=bool)
                left[list(lost)] = False
                self.consistency(self.zero, sigma, left)
                try:
                    self.wrench_from(self.zero, left)
                except ValueError:
                    pass  # these chips miss an axis: a cycle is refused the same way

    def consistency(self, b: np.ndarray, sigma: np.ndarray, chips: np.ndarray) -> Consistency:
        """How well the chips where ``chips`` is true agree with one deflection.

        The forward model b - b0 = H xi (+ room u, + gradient g, when set) over the channels S
        of those chips, each channel whitened by its noise ``sigma`` (T, one per channel):
        the weighted least-squares twist xi_hat and the residual r = W_S (b_S - b0_S) -
        W_S H_S xi_hat, whose squared norm under noise alone follows a chi-square with
        |S| - 6 (- 3 - k) degrees of freedom. Beside it, for each chip in use, the same
        squared norm with that chip left out: the chip whose leaving drops it most is the
        one that disagrees with the others. Needs H.

        One product a sample (`ConsistencyMaps`, built once for these chips and noise).
        """
        if self.H is None:
            raise ValueError("this calibration has no flux model H: no redundancy to check")
        last = self._last_check
        if last is not None and last[0] is chips and last[1] is sigma:
            return last[2].apply(b - self.zero)  # the same read-only arrays as last time: the same maps
        chips = np.asarray(chips, dtype=bool)
        maps = self._maps(chips, sigma)
        if not chips.flags.writeable and not sigma.flags.writeable:  # nobody changes them: kept by identity
            self._last_check = (chips, sigma, maps)
        return maps.apply(b - self.zero)

    def folded(
        self,
        sigma: np.ndarray,
        scale: np.ndarray | None,
        shift: np.ndarray | None,
        load_offset: np.ndarray,
        load_scale: np.ndarray,
        bound_scale: np.ndarray,
    ) -> FoldedCheck | None:
        """`consistency` of every chip and the wrench in one product (`FoldedCheck`, which says
        what the loads are), the flux brought to the reference temperature by b scale - shift
        (None: as read) first; None without H or with no redundancy to check."""
        if self.H is None:
            return None
        maps = self._maps(np.ones(self.A.shape[1] // 3, dtype=bool), sigma)
        if maps.maps is None:
            return None
        return FoldedCheck(maps, self.KA, self.zero, scale, shift, load_offset, load_scale, bound_scale)

    def _maps(self, chips: np.ndarray, sigma: np.ndarray) -> ConsistencyMaps:
        """The consistency maps of ``chips`` (bool, one per chip) at channel noise ``sigma``, built once."""
        key = chips.tobytes() + sigma.tobytes()
        maps = self._checks.get(key)
        if maps is None:
            maps = self._checks[key] = ConsistencyMaps(
                self.columns, self.K, sigma, chips, 0 if self.gradient is None else self.gradient.shape[1]
            )
        return maps


def tip_wrench(wrenches: list[np.ndarray], tip_to_sensor: list[np.ndarray]) -> np.ndarray:
    """w_tip = sum_i X(T_tip,i) w_i, the paper's Ad_1 w_1 + Ad_2 w_2 (section V-E).

    ``tip_to_sensor[i]`` is sensor i's frame seen from the tip frame (4x4, m);
    for sensors parallel to the tip it is a pure translation p_i/tip.
    """
    return sum(
        (se3.wrench_transform(T) @ w for T, w in zip(tip_to_sensor, wrenches, strict=True)), start=np.zeros(6)
    )
