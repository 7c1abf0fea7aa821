"""Does a plan's wrenches excite all six axes, each on its own? (section VII-B: with one
lever arm the torques are a fixed function of the forces and K is not identified.)

The wrenches are judged scaled by the sensor's range and centred: a direction the plan
hardly varies is named as the axes that make it up, with the condition number."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ftsensord.calibration.dataset import AXES
from ftsensord.model.linear import SENSOR_RANGE

#: Excitation test on the wrenches, each axis scaled by the sensor's range and
#: centred: a direction excited less than 1e-3 of the strongest is below what a
#: calibration rig knows its loads to (masses and lever arms to about 0.1 %),
#: so K along it would be fitted to rig error. Also the condition-number limit.
EXCITATION_TOL = 1e-3
#: A tied axis is explained by another axis when that one carries at least this
#: share of its variation: enough to name a partner, not every trace of round-off.
PARTNER_SHARE = 0.1
#: Condition number above which a plan is warned of (and a K that is not positive
#: definite is explained by it): K's error along the weakest direction grows with it.
#: The paper's six-axis plan stands at 85-90 (its forces reach 4 % of their range, its
#: torques all of theirs: benchmarks/robustness/pathological.py's sources); above 150 a direction
#: is excited little more than half as well as that plan's weakest.
CONDITION_WARN = 150.0
#: A component of a weak direction is named when it is at least this share of it:
#: enough to say which axes make it up without listing every trace.
DIRECTION_SHARE = 0.2


@dataclass(frozen=True)
class Excitation:
    """How well the wrenches of a dataset excite the six axes.

    ``singular_values`` are those of the centred, range-scaled wrench matrix;
    ``not_excited`` lists axes that hardly vary; ``tied`` lists groups of axes
    that vary only together (each a linear function of the others).
    """

    singular_values: np.ndarray
    not_excited: list[str]
    tied: list[list[str]]
    #: The right singular vectors (rows, range-scaled axes), strongest first.
    directions: np.ndarray | None = None

    @property
    def rank(self) -> int:
        s = self.singular_values
        return int(np.sum(s > EXCITATION_TOL * s[0])) if s[0] > 0 else 0

    @property
    def condition(self) -> float:
        s = self.singular_values
        return math.inf if s[-1] == 0 else float(s[0] / s[-1])

    @property
    def identifiable(self) -> bool:
        return self.rank == 6 and self.condition <= 1 / EXCITATION_TOL

    def describe(self) -> list[str]:
        """Plain words: 'Mz is not excited', 'Mx and Fy always vary together'."""
        out = [f"{a} is not excited" for a in self.not_excited]
        for group in self.tied:
            out.append(" and ".join(group) + " always vary together")
        if not out and not self.identifiable:
            out.append(self.explain())
        return out

    def weakest(self) -> str:
        """The load direction the plan excites least, in range-scaled axes, with its
        share of the strongest: '0.71 Fx - 0.70 My (0.19 % of the strongest)'."""
        if self.directions is None or len(self.directions) < 6:
            return "the sixth direction (fewer poses than axes)"
        v = self.directions[5] * np.sign(self.directions[5][np.argmax(np.abs(self.directions[5]))])
        terms = [f"{c:+.2f} {a}" for c, a in zip(v, AXES) if abs(c) >= DIRECTION_SHARE]
        share = self.singular_values[5] / self.singular_values[0] if self.singular_values[0] else 0.0
        return " ".join(terms).lstrip("+") + f" ({100 * share:.2g} % of the strongest)"

    def explain(self) -> str:
        """Why K is poorly determined: the condition number and the direction lacking."""
        return (
            f"the plan's wrenches are nearly dependent (condition number {self.condition:.3g}; above "
            f"{CONDITION_WARN:g} K is fitted to the rig's error along the direction it lacks: "
            f"{self.weakest()}, range-scaled)"
        )

    def advice(self) -> str:
        forces, torques = {"Fx", "Fy", "Fz"}, {"Mx", "My", "Mz"}
        involved = set(self.not_excited) | {a for g in self.tied for a in g}
        force_only = set(self.not_excited) & forces or any(set(g) <= forces for g in self.tied)
        tips = []
        if not involved or involved & torques:
            tips.append(
                "add poses whose lever arm points off the shaft axis (e.g. along x and along y), "
                "or a torque fixture, so that every torque varies independently of the forces"
            )
        if not involved or force_only:
            tips.append("add orientations that turn gravity along every axis of the sensor")
        return "; ".join(tips)


def check_excitation(wrench: np.ndarray) -> Excitation:
    """Excitation of the six wrench axes by ``wrench`` (n, 6; N, Nm)."""
    scaled = (wrench - wrench.mean(axis=0)) / SENSOR_RANGE
    _, s, vt = np.linalg.svd(scaled, full_matrices=False)
    s = np.concatenate([s, np.zeros(6 - len(s))])  # fewer poses than axes
    std = scaled.std(axis=0)
    excited = std > EXCITATION_TOL * std.max() if std.max() > 0 else np.zeros(6, dtype=bool)
    not_excited = [AXES[k] for k in range(6) if not excited[k]]
    groups: list[set[int]] = []
    for k in np.flatnonzero(excited):
        others = [j for j in np.flatnonzero(excited) if j != k]
        if not others:
            continue
        coef, *_ = np.linalg.lstsq(scaled[:, others], scaled[:, k], rcond=None)
        residual = scaled[:, k] - scaled[:, others] @ coef
        if residual.std() > EXCITATION_TOL * std[k]:
            continue  # axis k varies on its own
        share = np.abs(coef) * std[others] / std[k]
        group = {int(k)} | {int(j) for j, sh in zip(others, share) if sh >= PARTNER_SHARE}
        for g in [g for g in groups if g & group]:
            group |= g
            groups.remove(g)
        groups.append(group)
    tied = sorted([[AXES[k] for k in sorted(g)] for g in groups])
    return Excitation(s, not_excited, tied, vt)
