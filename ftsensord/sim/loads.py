"""Loads over time: the wrench [f; m] (N, Nm) on a sensor's centre piece,
expressed in the sensor's frame {0}, as a function of time t (s).

The calibration robot of the paper's section VII-B is here too: a robot turns
the sensor through many orientations with a known mass on a rod fixed to the
centre piece; the wrench is the mass's weight moved to {0} by the adjoint.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ..model import se3

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
        if (self.times_s.ndim != 1 or len(self.times_s) < 1 or self.wrenches.shape != (len(self.times_s), 6)
                or np.any(np.diff(self.times_s) <= 0) or not np.all(np.isfinite(self.wrenches))):
            raise ValueError("a recorded load needs increasing times and one finite 6-vector per time")

    def wrench(self, t: float) -> np.ndarray:
        return np.array([np.interp(t, self.times_s, self.wrenches[:, k]) for k in range(6)])


def ramp(from_s: float, to_s: float, start: np.ndarray, end: np.ndarray) -> RecordedLoad:
    return RecordedLoad(np.array([from_s, to_s]), np.stack([_wrench(start), _wrench(end)]))


@dataclass(frozen=True)
class CalibrationPose:
    """One robot pose: gravity's direction seen in frame {0} (unit), the mass
    (kg) and the lever arm from {0}'s origin to the mass's centre (m, in {0})."""

    gravity_dir: np.ndarray
    mass_kg: float
    lever_m: np.ndarray

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
    """The robot holds each pose for ``dwell_s`` in turn, then the last one."""

    poses: list[CalibrationPose]
    dwell_s: float = 1.0

    def wrench(self, t: float) -> np.ndarray:
        k = min(max(int(t // self.dwell_s), 0), len(self.poses) - 1)
        return self.poses[k].wrench()


#: Lever arms (m, frame {0}) from the sensor's centre to the mass: one along the
#: shaft as in the paper's rod, and three off it so that Mz and the other torques
#: vary independently of the forces. 200 g at 0.1 m gives 0.196 Nm, the range.
SIX_AXIS_ARMS = ((0.0, 0.0, 0.10), (0.07, 0.0, 0.07), (0.0, 0.07, 0.07), (-0.05, -0.05, 0.05))
#: The paper's original plan: the rod only (torques are then fixed by the forces).
ONE_ARM = ((0.0, 0.0, 0.10),)
PLANS = {"six-axis": SIX_AXIS_ARMS, "one-arm": ONE_ARM}


def fibonacci_directions(n: int, offset: float = 0.5) -> np.ndarray:
    """``n`` unit vectors spread evenly over the sphere (a Fibonacci lattice)."""
    k = np.arange(n) + offset
    z = 1 - 2 * k / n
    phi = k * math.pi * (3 - math.sqrt(5))
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def paper_plan(plan: str = "six-axis", n_fit: int = 193, n_validation: int = 60,
               fit_masses: Sequence[float] = (0.05, 0.2), validation_mass: float = 0.1,
               ) -> list[tuple[CalibrationPose, str]]:
    """The paper's procedure (section VII-B): ``n_fit`` orientations with 50 g and
    200 g, validation with 100 g in other orientations; lever arms per ``plan``."""
    if plan not in PLANS:
        raise ValueError(f"plan must be one of {sorted(PLANS)}, got {plan!r}")
    arms = [np.array(a) for a in PLANS[plan]]
    poses = [(CalibrationPose(d, fit_masses[k % len(fit_masses)], arms[k % len(arms)]), "fit")
             for k, d in enumerate(fibonacci_directions(n_fit))]
    poses += [(CalibrationPose(d, validation_mass, arms[k % len(arms)]), "validation")
              for k, d in enumerate(fibonacci_directions(n_validation, offset=0.25))]
    return poses
