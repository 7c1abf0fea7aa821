"""Loads over time: the wrench [f; m] (N, Nm) on a sensor's centre piece,
expressed in the sensor's frame {0}, as a function of time t (s); and the
sensor's orientation over time, R_w0 (frame {0} in the world), which turns the
room's field into the sensor's frame.

The calibration robot of the paper's section VII-B is here too: a robot turns
the sensor through many orientations with a known mass on a rod fixed to the
centre piece; the wrench is the mass's weight moved to {0} by the adjoint, and
the robot's orientation is the sensor's.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ftsensord.model import se3

#: Standard gravity, m/s^2.
G = 9.80665


class Load(Protocol):
    def wrench(self, t: float) -> np.ndarray:
        """The wrench [f; m] (N, Nm) in frame {0} at time ``t`` (s)."""
        ...


def _wrench(w: object) -> np.ndarray:
    arr = np.asarray(w, dtype=float)
    if arr.shape != (6,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"a wrench is 6 finite numbers [fx fy fz mx my mz], got {w!r}")
    return arr


@dataclass
class StaticLoad:
    w: np.ndarray

    def __post_init__(self) -> None:
        self.w = _wrench(self.w)

    def wrench(self, t: float) -> np.ndarray:
        return self.w


NO_LOAD = StaticLoad(np.zeros(6))


@dataclass
class StepLoad:
    """``before`` until ``at_s``, ``after`` from then on."""

    at_s: float
    before: np.ndarray
    after: np.ndarray

    def __post_init__(self) -> None:
        self.before, self.after = _wrench(self.before), _wrench(self.after)

    def wrench(self, t: float) -> np.ndarray:
        return self.after if t >= self.at_s else self.before


@dataclass
class RecordedLoad:
    """A recorded sequence, linearly interpolated and held at both ends.
    A ramp is a recording of two points."""

    times_s: np.ndarray
    wrenches: np.ndarray

    def __post_init__(self) -> None:
        self.times_s = np.asarray(self.times_s, dtype=float)
        self.wrenches = np.asarray(self.wrenches, dtype=float)
        if (
            self.times_s.ndim != 1
            or len(self.times_s) < 1
            or self.wrenches.shape != (len(self.times_s), 6)
            or np.any(np.diff(self.times_s) <= 0)
            or not np.all(np.isfinite(self.wrenches))
        ):
            raise ValueError("a recorded load needs increasing times and one finite 6-vector per time")

    def wrench(self, t: float) -> np.ndarray:
        return np.array([np.interp(t, self.times_s, self.wrenches[:, k]) for k in range(6)])


def ramp(from_s: float, to_s: float, start: np.ndarray, end: np.ndarray) -> RecordedLoad:
    return RecordedLoad(np.array([from_s, to_s]), np.stack([_wrench(start), _wrench(end)]))


# --- orientation over time -------------------------------------------------------------
#: World frame: z up, so gravity is -z (and x north, y west for a room field in
#: north-east-down figures turned into it: docs/design/scenes.md).
DOWN = np.array([0.0, 0.0, -1.0])


def _rotation(R: object) -> np.ndarray:
    arr = np.asarray(R, dtype=float)
    # 1e-9: far above round-off of a product of a few rotations, far below any real turn.
    if arr.shape != (3, 3) or not np.allclose(arr.T @ arr, np.eye(3), atol=1e-9) or np.linalg.det(arr) <= 0:
        raise ValueError(f"a rotation is a 3 x 3 orthonormal matrix of determinant +1, got {R!r}")
    return arr


class Orientation(Protocol):
    def rotation(self, t: float) -> np.ndarray:
        """R_w0 (3 x 3): the sensor's frame {0} seen in the world at time ``t`` (s)."""
        ...


@dataclass
class FixedOrientation:
    """The sensor held still: R_w0 = exp(rotvec) (rad)."""

    R: np.ndarray

    def __post_init__(self) -> None:
        self.R = _rotation(self.R)

    @classmethod
    def from_rotvec_deg(cls, rotvec_deg: object) -> FixedOrientation:
        return cls(se3.exp_so3(np.radians(np.asarray(rotvec_deg, dtype=float))))

    def rotation(self, t: float) -> np.ndarray:
        return self.R


IDENTITY = FixedOrientation(np.eye(3))


@dataclass
class RecordedOrientation:
    """A recorded sequence of orientations, held at both ends and interpolated
    between samples along the shortest rotation (slerp):
    R(t) = R_k exp(s log(R_k^T R_k+1)), s = (t - t_k) / (t_k+1 - t_k).

    Why not component-wise on the rotation vectors: a rotation vector is not
    linear in the motion, so interpolating its components turns about a wrong,
    time-varying axis and at a non-uniform rate (wildly so where the vectors pass
    near 180 deg, where the same rotation has two vectors); the geodesic is what a
    constant angular velocity between two samples would do, which is the honest
    assumption between a recording's samples.
    """

    times_s: np.ndarray
    rotations: np.ndarray

    def __post_init__(self) -> None:
        self.times_s = np.asarray(self.times_s, dtype=float)
        if (
            self.times_s.ndim != 1
            or len(self.times_s) < 1
            or np.any(np.diff(self.times_s) <= 0)
            or len(self.rotations) != len(self.times_s)
        ):
            raise ValueError("a recorded orientation needs increasing times and one rotation per time")
        self.rotations = np.array([_rotation(R) for R in self.rotations])
        self._steps = [se3.log_so3(a.T @ b) for a, b in zip(self.rotations[:-1], self.rotations[1:])]

    @classmethod
    def from_rotvecs_deg(cls, times_s: object, rotvecs_deg: object) -> RecordedOrientation:
        return cls(
            np.asarray(times_s, dtype=float),
            np.array([se3.exp_so3(np.radians(w)) for w in np.asarray(rotvecs_deg, dtype=float)]),
        )

    def rotation(self, t: float) -> np.ndarray:
        times = self.times_s
        if t <= times[0]:
            return self.rotations[0]
        if t >= times[-1]:
            return self.rotations[-1]
        k = int(np.searchsorted(times, t, side="right")) - 1
        s = (t - times[k]) / (times[k + 1] - times[k])
        return self.rotations[k] @ se3.exp_so3(s * self._steps[k])


def gravity_to_down(gravity_dir: np.ndarray, yaw_rad: float = 0.0) -> np.ndarray:
    """R_w0 that turns ``gravity_dir`` (unit, in {0}) onto the world's down, then
    turns the sensor by ``yaw_rad`` about the vertical (which gravity cannot see,
    and a room field can).

    The shortest turn taking g to down is about g x down; at g = up exactly that
    axis vanishes and any horizontal axis does: x is taken (tested).
    """
    g = np.asarray(gravity_dir, dtype=float)
    g = g / np.linalg.norm(g)
    axis = np.cross(g, DOWN)
    sin_a, cos_a = float(np.linalg.norm(axis)), float(g @ DOWN)
    if sin_a == 0.0:
        # g = down: no turn; g = up: a half turn about x (any horizontal axis would do).
        base = np.eye(3) if cos_a > 0 else se3.exp_so3(np.array([np.pi, 0.0, 0.0]))
    else:
        base = se3.exp_so3(axis / sin_a * np.arctan2(sin_a, cos_a))
    return se3.exp_so3(np.array([0.0, 0.0, yaw_rad])) @ base


# --- the calibration robot -----------------------------------------------------------------
@dataclass(frozen=True)
class CalibrationPose:
    """One robot pose: gravity's direction seen in frame {0} (unit), the mass
    (kg) and the lever arm from {0}'s origin to the mass's centre (m, in {0}).

    ``rotation`` is R_w0, the sensor's full orientation in the world (z up), as
    the robot knows it from its joints; gravity fixes it only up to a turn about
    the vertical, which a room field does see. When not given, the turn taking
    gravity straight down is assumed (`gravity_to_down`).
    """

    gravity_dir: np.ndarray
    mass_kg: float
    lever_m: np.ndarray
    rotation: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.rotation is not None:
            R = _rotation(self.rotation)
            g = np.asarray(self.gravity_dir, dtype=float)
            # 1e-6 (0.2 arcsec): the two are written from one robot pose; any larger
            # disagreement is a pose recorded wrong, which would corrupt both fits.
            if not np.allclose(R.T @ DOWN, g / np.linalg.norm(g), atol=1e-6):
                raise ValueError(
                    f"rotation and gravity_dir disagree: R^T down = {R.T @ DOWN}, gravity_dir = {g}"
                )

    def orientation(self) -> np.ndarray:
        """R_w0 at this pose."""
        return self.rotation if self.rotation is not None else gravity_to_down(self.gravity_dir)

    def wrench(self) -> np.ndarray:
        """w = X_{0,w} [0 0 -m g 0 0 0]: the weight at the mass, moved to {0}.

        With the mass frame's orientation taken so that gravity is ``gravity_dir``
        in {0}, this is the paper's Ad^T w_omega: f = m g dir, m = lever x f.
        """
        T = se3.pose(p=self.lever_m)
        f = self.mass_kg * G * np.asarray(self.gravity_dir, dtype=float)
        return se3.wrench_transform(T) @ np.concatenate([f, np.zeros(3)])


@dataclass
class CalibrationRobotLoad:
    """The robot holds each pose for ``dwell_s`` in turn, then the last one. It is
    the sensor's load and its orientation at once (an `Orientation` too)."""

    poses: list[CalibrationPose]
    dwell_s: float = 1.0

    def _pose(self, t: float) -> CalibrationPose:
        return self.poses[min(max(int(t // self.dwell_s), 0), len(self.poses) - 1)]

    def wrench(self, t: float) -> np.ndarray:
        return self._pose(t).wrench()

    def rotation(self, t: float) -> np.ndarray:
        return self._pose(t).orientation()


#: The flange's centre, 4 mm above the sensor's (m, frame {0}): a mass hung there loads the
#: forces with almost no torque (4 kg at 4 mm is 0.16 Nm, within the range).
FLANGE_CENTRE = (0.0, 0.0, 0.004)
#: Lever arms (m, frame {0}) from the sensor's centre to the mass: one along the
#: shaft as in the paper's rod, three off it so that Mz and the other torques
#: vary independently of the forces (200 g at 0.1 m gives 0.196 Nm, the range), and one at
#: the flange's centre, so that forces also come without the long arms'
#: torques. Without that one, a lateral force always came with its 50-100 mm arm's torque,
#: and K A, fitted to be right there, read a force along y alone about 10 % low
#: (`benchmarks.accuracy.axis_gain`; docs/design/estimators.md, "A load along one axis").
SIX_AXIS_ARMS = (
    (0.0, 0.0, 0.10),
    (0.07, 0.0, 0.07),
    (0.0, 0.07, 0.07),
    (-0.05, -0.05, 0.05),
    FLANGE_CENTRE,
)
#: The paper's original plan: the rod only (torques are then fixed by the forces).
ONE_ARM = ((0.0, 0.0, 0.10),)
PLANS = {"six-axis": SIX_AXIS_ARMS, "one-arm": ONE_ARM}
#: Check poses (split "check"): the loads a tool meets, where the part's departures from the
#: model show (magnets glued tilted, silicone that stiffens; invisible at 50-200 g):
#: 1, 2 and 4 kg hung at the flange's centre, so |F| reaches 39 N with the torque at
#: 0.16 Nm, within the range (a 4 kg mass on the rod's 0.1 m would be 20x it).
CHECK_MASSES = (1.0, 2.0, 4.0)
CHECK_ARM = FLANGE_CENTRE


#: The step-and-hold segment a calibration run ends with (docs/guide/calibration.md): each of its
#: two poses held this long (s), the chips read every `HOLD_PERIOD_S` (s). 60 s: the
#: identification searches retardation times up to the hold, and the default series' slower
#: one is 32 s; 10 ms: the daemon's own period, 2.6x fewer readings than the bus's fastest.
HOLD_S, HOLD_PERIOD_S = 60.0, 0.01


def fibonacci_directions(n: int, offset: float = 0.5) -> np.ndarray:
    """``n`` unit vectors spread evenly over the sphere (a Fibonacci lattice)."""
    k = np.arange(n) + offset
    z = 1 - 2 * k / n
    phi = k * math.pi * (3 - math.sqrt(5))
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


#: The robot's turn about the vertical from one pose to the next: the golden angle,
#: so that any run of poses faces the room's horizontal field from spread directions.
YAW_STEP_RAD = math.pi * (3 - math.sqrt(5))


def paper_plan(
    plan: str = "six-axis",
    n_fit: int = 193,
    n_validation: int = 60,
    fit_masses: Sequence[float] = (0.05, 0.2),
    validation_mass: float = 0.1,
    n_no_load: int = 0,
    n_check: int = 0,
) -> list[tuple[CalibrationPose, str]]:
    """The paper's procedure (section VII-B): ``n_fit`` orientations with 50 g and
    200 g, validation with 100 g in other orientations; lever arms per ``plan``.

    Each pose carries the robot's full orientation: gravity along the pose's
    direction, turned about the vertical by `YAW_STEP_RAD` more at every pose.
    ``n_no_load`` poses (split "no-load", rod and mass off) at further orientations, first in
    the list, record what the room's field alone does to the chips (docs/guide/calibration.md); ``n_check``
    poses (split "check", `CHECK_MASSES` on `CHECK_ARM`) the model's accuracy at large loads.
    """
    if plan not in PLANS:
        raise ValueError(f"plan must be one of {sorted(PLANS)}, got {plan!r}")
    arms = [np.array(a) for a in PLANS[plan]]
    poses: list[tuple[CalibrationPose, str]] = []

    def add(d: np.ndarray, mass: float, arm: np.ndarray, split: str) -> None:
        R = gravity_to_down(d, YAW_STEP_RAD * len(poses))
        poses.append((CalibrationPose(R.T @ DOWN, mass, arm, R), split))

    for k, d in enumerate(fibonacci_directions(n_fit)):
        add(d, fit_masses[k % len(fit_masses)], arms[k % len(arms)], "fit")
    for k, d in enumerate(fibonacci_directions(n_validation, offset=0.25)):
        add(d, validation_mass, arms[k % len(arms)], "validation")
    for d in fibonacci_directions(n_no_load, offset=0.75):
        add(d, 0.0, np.zeros(3), "no-load")
    for k, d in enumerate(fibonacci_directions(n_check, offset=0.1)):
        add(d, CHECK_MASSES[k % len(CHECK_MASSES)], np.array(CHECK_ARM), "check")
    # The robot's order: the no-load poses first, before any mass touches the rod (the same
    # orientations, drawn above): a silicone that creeps carries a load's after-effect into
    # the poses after it for minutes, where the room check would see it (docs/guide/calibration.md).
    return [p for p in poses if p[1] == "no-load"] + [p for p in poses if p[1] != "no-load"]
