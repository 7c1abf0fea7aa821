"""A person following a guided calibration's prompts (docs/guide/guided-calibration.md), with
the errors a person makes: the scene's ``[person]`` table (docs/design/scenes.md).

Told "face k down, m g on hook h", the person sets the holder down on a face (the one asked,
or once in a while a neighbour), seated a little off (a crumb, a warped print), turned about
the vertical anyhow (nobody aims that), hangs the mass (or forgets it, or picks another hook)
and now and then bumps the table while the chips are read. Each mass and hook is off by its
own fixed error, within its tolerance: the same mass is the same wrong every time.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ftsensord.docfile import Table
from ftsensord.model import se3
from ftsensord.sim.loads import gravity_to_down

#: The keys of ``[person]``, their default (the typical person the figures are read on) and
#: largest accepted value. Defaults: a face seated 1-2 deg off (1.5 deg standard deviation),
#: hooks +-0.5 mm, masses +-0.5 % (an inexpensive hooked set), the arm weighed to +-1 g on a
#: kitchen scale; a bump in 1 step of 30, a neighbouring face in 1 of 50, a hook forgotten or
#: mistaken in 1 of 100. The limits: past them it is not a person's slip but another procedure.
PERSON_KEYS: dict[str, tuple[float, float, str]] = {
    "face_tilt_deg": (1.5, 10.0, "deg, standard deviation"),
    "lever_arm_mm": (0.5, 5.0, "mm, each hook's error within +-"),
    "mass_tolerance_pct": (0.5, 10.0, "%, each mass's error within +-"),
    "arm_mass_g": (1.0, 10.0, "g, the arm's weighing within +-"),
    "bump_rate": (1 / 30, 0.5, "share of steps"),
    "wrong_face_rate": (0.02, 0.5, "share of steps"),
    "missing_mass_rate": (0.01, 0.5, "share of steps"),
    "wrong_hook_rate": (0.01, 0.5, "share of steps"),
}
#: A bump: a knock on the table felt at the centre piece as this force (N, a random
#: direction) for `BUMP_S` (s), within the pose's reading.
BUMP_N, BUMP_S = (1.0, 4.0), 0.1
#: Neighbouring faces: within this angle of the one asked (deg): a rhombicuboctahedron's
#: are 35 and 45 deg apart, its next ring 60 deg and more.
NEIGHBOUR_DEG = 50.0


@dataclass(frozen=True)
class Act:
    """What the person did: gravity in {0} (unit), the orientation R_w0, the face, mass (g)
    and hook used, their actual lever arm (mm) and mass (g), and a bump (start within the
    reading as a share of it, force in {0}, N) or None; ``slips`` names the mistakes made."""

    gravity: np.ndarray
    rotation: np.ndarray
    face: int
    mass_g: float
    hook: str
    slips: tuple[str, ...]
    bump: tuple[float, np.ndarray] | None = None


@dataclass
class Person:
    face_tilt_deg: float = PERSON_KEYS["face_tilt_deg"][0]
    lever_arm_mm: float = PERSON_KEYS["lever_arm_mm"][0]
    mass_tolerance_pct: float = PERSON_KEYS["mass_tolerance_pct"][0]
    arm_mass_g: float = PERSON_KEYS["arm_mass_g"][0]
    bump_rate: float = PERSON_KEYS["bump_rate"][0]
    wrong_face_rate: float = PERSON_KEYS["wrong_face_rate"][0]
    missing_mass_rate: float = PERSON_KEYS["missing_mass_rate"][0]
    wrong_hook_rate: float = PERSON_KEYS["wrong_hook_rate"][0]
    seed: int = 0
    _fixed: dict[str, float | np.ndarray] = field(default_factory=dict, repr=False)

    @classmethod
    def careful(cls, seed: int = 0) -> Person:
        """A person who makes no mistake and seats every face exactly (tests' reference)."""
        return cls(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, seed)

    def rng(self, step: int, attempt: int) -> np.random.Generator:
        """The draws of one attempt at one step: the same on a resumed run."""
        return np.random.default_rng([self.seed, step, attempt])

    def mass_error(self, key: str) -> float:
        """The fixed relative error of the mass (or arm) called ``key``."""
        if key not in self._fixed:
            rng = np.random.default_rng([self.seed, sum(key.encode()), len(key)])
            share = self.arm_mass_g if key == "arm" else self.mass_tolerance_pct * 1e-2
            self._fixed[key] = float(rng.uniform(-1.0, 1.0) * share)
        return float(self._fixed[key])

    def hook_error_mm(self, hook: str) -> np.ndarray:
        """The fixed error (mm) of hook ``hook``'s place on the printed arm."""
        key = f"hook {hook}"
        if key not in self._fixed:
            rng = np.random.default_rng([self.seed, ord(hook[0]), 7])
            self._fixed[key] = rng.uniform(-1.0, 1.0, 3) * self.lever_arm_mm
        return np.asarray(self._fixed[key])

    def act(
        self,
        step: int,
        attempt: int,
        face: int,
        mass_g: float,
        hook: str,
        normals: np.ndarray,
        hooks: list[str],
    ) -> Act:
        """Do step ``step`` (its ``attempt``-th try): face ``face`` (1-based in ``normals``)
        down, ``mass_g`` on ``hook`` (0: the arm off)."""
        rng = self.rng(step, attempt)
        slips = []
        if rng.random() < self.wrong_face_rate:
            near = np.degrees(np.arccos(np.clip(normals @ normals[face - 1], -1, 1)))
            others = np.flatnonzero((near > 1.0) & (near < NEIGHBOUR_DEG))
            face = int(rng.choice(others)) + 1
            slips.append(f"face {face} down")
        if mass_g > 0 and rng.random() < self.missing_mass_rate:
            mass_g = 0.0
            slips.append("no mass on the hook")
        elif mass_g > 0 and rng.random() < self.wrong_hook_rate:
            hook = str(rng.choice([h for h in hooks if h != hook]))
            slips.append(f"hook {hook}")
        # Seated off: the face's normal tilted by a small turn about a random horizontal axis.
        axis = np.cross(normals[face - 1], rng.normal(size=3))
        axis /= np.linalg.norm(axis)
        tilt = se3.exp_so3(axis * np.radians(rng.normal(0.0, self.face_tilt_deg)))
        gravity = tilt @ normals[face - 1]
        rotation = gravity_to_down(gravity, rng.uniform(0.0, 2 * np.pi))
        bump = None
        if rng.random() < self.bump_rate:
            d = rng.normal(size=3)
            bump = (float(rng.uniform(0.0, 0.8)), d / np.linalg.norm(d) * rng.uniform(*BUMP_N))
            slips.append("a bump")
        return Act(rotation.T @ np.array([0.0, 0.0, -1.0]), rotation, face, mass_g, hook, tuple(slips), bump)


def parse_person(t: Table) -> Person:
    """A scene's ``[person]`` table; an empty one is the typical person."""
    t.only({*PERSON_KEYS, "seed"})
    values = {
        k: t.number(k, default, low=0.0, high=high, unit=unit)
        for k, (default, high, unit) in PERSON_KEYS.items()
    }
    return Person(
        values["face_tilt_deg"],
        values["lever_arm_mm"],
        values["mass_tolerance_pct"],
        values["arm_mass_g"],
        values["bump_rate"],
        values["wrong_face_rate"],
        values["missing_mass_rate"],
        values["wrong_hook_rate"],
        seed=t.integer("seed", 0, low=0, what="an integer >= 0 naming the person's draws"),
    )
