"""The printed fixture of a guided calibration (no robot): a holder and a hook arm, and the
plan a person follows with them (docs/guide/guided-calibration.md).

The holder is a polyhedron around the sensor: the intersection of `FACE_NORMALS`' half-spaces,
every face at ``face_mm`` from the sensor's centre. Set down on face k, its outward normal n_k
(frame {0}) points down: gravity in {0} is n_k, the way the robot's joints give it. Every face
touches the sphere of radius ``face_mm`` at its centre point, so the holder stands on each of
them (the centre of mass, near the sensor's centre, projects inside the face).

The hook arm is clamped on the tool flange after the no-load poses; its stem rises up the bore
to just above the holder, where its branches start. `HOOKS` are its hooks' lever arms (mm,
{0}): A, C and D at the ends of branches, three of the robot plan's four long arms
(`sim.loads.SIX_AXIS_ARMS`), so the torques vary apart from the forces; E at the foot of a leg
(`LEGS`) that hangs from the fourth branch's end down beside the holder, level with the
sensor's centre. E stands in for the robot's fifth arm, at the flange's centre, which lies
inside the holder: a lever arm with z = 0 gives forces without the long arms' torques (a force
along x none, one along y Mz alone), so that the linear map is not fitted only where Fy comes
with Mx = -z Fy (it then read a force along y alone about 10 % low). Its own weight (weighed,
``arm_g``, at ``arm_com_mm``) is part of every loaded pose's wrench: one mass at the weighted
centre of the two.

The plan is the robot's in shape: no-load poses first (the arm off: what the room's field
alone does), then 200 g on every hook, face by face, and 100 g validation poses.
A face that would put a hook, or the arm's stem or a hook's leg, below the table top is left
out for that hook (`Fixture.clears_table`).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np

from ftsensord.calibration.excitation import Excitation, check_excitation
from ftsensord.calibration.relaxation import settle_s
from ftsensord.model.viscoelastic import Relaxation
from ftsensord.sim.loads import CalibrationPose, gravity_to_down


def _rhombicuboctahedron() -> np.ndarray:
    """Its 26 face normals: 6 along the axes, 12 along the edges' diagonals, 8 along the
    corners' (the directions a cube's faces, edges and corners point)."""
    axes = [v for v in itertools.product((-1, 0, 1), repeat=3) if any(v)]
    return np.array(
        [np.array(v) / np.linalg.norm(v) for v in sorted(axes, key=lambda v: (sum(map(abs, v)), v))]
    )


#: The holder's outward face normals (frame {0}), numbered from 1 in this order.
FACE_NORMALS = _rhombicuboctahedron()
#: The hook arm's hooks (mm, frame {0}): A, C and D at the ends of its branches (three of the
#: robot's long arms), E at the foot of a leg level with the sensor's centre (its lever arm's z
#: is 0: a force along x gives no torque, one along y gives Mz alone). There is no B: E takes
#: the place of the robot's fourth arm, (70, 0, 70), and the plan keeps its length (measured on
#: parts 61-63, one arm weight for all: with B kept beside E the plan had 17 steps more and was
#: no better, the worst axis 1.42-1.49 times the robot's error against 1.25-1.35 without B;
#: without E, 1.50-1.74).
HOOKS = {"A": (0.0, 0.0, 100.0), "C": (0.0, 70.0, 70.0), "D": (-50.0, -50.0, 50.0), "E": (70.0, 0.0, 0.0)}
#: Legs (mm, frame {0}): a hook on a leg hangs below the end of a branch, the leg's top,
#: reaching down beside the holder (its faces at 45 mm: the leg at x = 70 passes them by 25).
LEGS = {"E": (70.0, 0.0, 50.0)}
#: A hook must stand this far above the table top (mm) for its mass to hang free past the
#: table's edge: the hook's own eye and a mass's hanger take about that.
HOOK_CLEARANCE_MM = 10.0
#: The rest of the arm that carries the mass (its stem's top, where the branches start, and
#: a leg's top) must not touch the table: this far above its top (mm), the rod's radius.
ROD_CLEARANCE_MM = 3.0
#: The arm is clamped on the flange at `CLAMP_MM` and its stem rises up the bore to
#: `STEM_TOP_MM`, just above the holder's top face (45 mm); its branches start there, above the
#: holder (mm, frame {0}).
CLAMP_MM, STEM_TOP_MM = (0.0, 0.0, 20.0), (0.0, 0.0, 50.0)
#: What a person takes per step besides the wait (s): turning the holder to a face and
#: hanging or swapping a mass, timed by hand on a mock-up (10-20 s).
HANDLING_S = 15.0
#: The silicone's creep still to come when a pose is read, as a share of the load's change:
#: 2 % of a 200 g step is 0.04 N, a fifth of Table II's smallest force error.
SETTLE_FRACTION = 0.02


@dataclass(frozen=True)
class Fixture:
    """The holder and hook arm's dimensions (mm, g): what the OpenSCAD file is drawn from."""

    face_mm: float = 45.0
    bore_mm: float = 36.0  # the sensor's shell sits in this bore
    hooks_mm: dict[str, tuple[float, float, float]] = field(default_factory=lambda: dict(HOOKS))
    legs_mm: dict[str, tuple[float, float, float]] = field(default_factory=lambda: dict(LEGS))
    # As designed: 20 g at (0, 0, 60) for the clamp, stem and branches, and 2 g for E's leg
    # (50 mm of the 6 mm rod in PLA, 1.8 g, and its hook) at (70, 0, 25).
    arm_g: float = 22.0
    arm_com_mm: tuple[float, float, float] = (6.4, 0.0, 56.8)

    @property
    def normals(self) -> np.ndarray:
        return FACE_NORMALS

    def hook_m(self, hook: str) -> np.ndarray:
        return np.array(self.hooks_mm[hook]) * 1e-3

    def clears_table(self, face: int, hook: str) -> bool:
        """Face ``face`` down (1-based): is hook ``hook`` at least `HOOK_CLEARANCE_MM` above the
        table, and the arm's stem top and the hook's leg's top, if it hangs on one, at least
        `ROD_CLEARANCE_MM` (the rods in between then are: an arm resting on the table would
        carry part of the load)?"""
        up = -self.normals[face - 1]

        def height(p: tuple[float, float, float]) -> float:
            return self.face_mm + float(up @ np.array(p))

        rods = [STEM_TOP_MM] + ([self.legs_mm[hook]] if hook in self.legs_mm else [])
        return height(self.hooks_mm[hook]) >= HOOK_CLEARANCE_MM and all(
            height(p) >= ROD_CLEARANCE_MM for p in rods
        )


@dataclass(frozen=True)
class Step:
    """One step of the plan: face ``face`` down (1-based), ``mass_g`` on ``hook`` (0 g: the arm
    off, a no-load pose), the split its pose goes to."""

    face: int
    mass_g: float
    hook: str
    split: str

    def instruction(self) -> str:
        if self.split == "no-load":
            return f"face {self.face} down, hook arm off"
        return f"face {self.face} down, {self.mass_g:g} g on hook {self.hook}"


def pose_of(
    fixture: Fixture,
    face: int,
    mass_g: float,
    hook: str,
    *,
    arm_on: bool = True,
    gravity: np.ndarray | None = None,
) -> CalibrationPose:
    """The pose a step asks for (or, with ``gravity``, the one a person made): the mass and the
    arm's weight as one mass at their weighted centre; no rotation (a person does not know the
    holder's turn about the vertical)."""
    g = fixture.normals[face - 1] if gravity is None else gravity
    if not arm_on:
        return CalibrationPose(g, 0.0, np.zeros(3))
    m, arm = mass_g * 1e-3, fixture.arm_g * 1e-3
    lever = (m * fixture.hook_m(hook) + arm * np.array(fixture.arm_com_mm) * 1e-3) / (m + arm)
    return CalibrationPose(g, m + arm, lever)


#: Masses of the plan (g): 200 g on every fit step, 100 g to validate. The robot's plan
#: alternates 50 g and 200 g over 193 poses; with 70 steps, the heavier mass on each (the
#: load 4 times the lighter's, the chips' noise and the person's errors alike) identifies K
#: better: on 3 parts Mz's error fell from 1.6-1.8 to 1.2-1.4 times the robot's, Fz's from
#: 1.2-1.5 to 1.2-1.4 (docs/results/accuracy.md).
FIT_MASS_G, VALIDATION_MASS_G = 200.0, 100.0
#: The masses of a hooked set a person may hang by mistake (g): what the check names.
KIT_MASSES_G = (50.0, 100.0, 200.0)


def guided_plan(
    fixture: Fixture = Fixture(), *, no_load: int = 12, every: int = 1, validation: int = 12
) -> list[Step]:
    """The steps in a person's order: ``no_load`` no-load poses on faces spread over the sphere
    (the arm off), then for each face every hook it clears with 200 g (``every`` keeps every
    n-th of those steps: a quick plan),
    then ``validation`` 100 g poses on faces and hooks the fit steps pair otherwise."""
    n = len(fixture.normals)
    spread = [int(k) for k in np.round(np.linspace(0, n - 1, no_load)).astype(int)] if no_load else []
    steps = [Step(k + 1, 0.0, "-", "no-load") for k in dict.fromkeys(spread)]
    pairs = [(f, h) for f in range(1, n + 1) for h in fixture.hooks_mm if fixture.clears_table(f, h)]
    picked = pairs[::every]
    fits = [Step(f, FIT_MASS_G, h, "fit") for f, h in picked]
    # Validation: spread over the pairs, offset from the fit's pick so that they differ.
    picks = (np.round(np.linspace(0, len(pairs) - 1, validation) + 0.5).astype(int) % len(pairs)).tolist()
    checks = [Step(pairs[k][0], VALIDATION_MASS_G, pairs[k][1], "validation") for k in picks]
    return steps + fits + checks


def plan_excitation(fixture: Fixture, steps: list[Step]) -> Excitation:
    """The excitation check the fit makes (`excitation.check_excitation`) on the plan's fit wrenches."""
    fits = [pose_of(fixture, s.face, s.mass_g, s.hook).wrench() for s in steps if s.split == "fit"]
    return check_excitation(np.array(fits))


def step_settle_s(relaxation: Relaxation | None) -> float:
    """The wait after a load changes before a pose is read (s): until the creep still to come
    is `SETTLE_FRACTION` of the change (`relaxation.settle_s`); 0 for a silicone without memory."""
    return 0.0 if relaxation is None else settle_s(relaxation, SETTLE_FRACTION)


def person_time_s(steps: list[Step], relaxation: Relaxation | None) -> float:
    """How long the plan takes a person: each step's handling and its wait."""
    return len(steps) * (HANDLING_S + step_settle_s(relaxation))


def as_dataset_poses(fixture: Fixture, steps: list[Step]) -> list[tuple[CalibrationPose, str]]:
    """The plan's poses as `rig.record_dataset` takes them (gravity straight down, no turn)."""
    out = []
    for s in steps:
        p = pose_of(fixture, s.face, s.mass_g, s.hook, arm_on=s.split != "no-load")
        out.append(
            (CalibrationPose(p.gravity_dir, p.mass_kg, p.lever_m, gravity_to_down(p.gravity_dir)), s.split)
        )
    return out


def openscad(fixture: Fixture = Fixture()) -> str:
    """The fixture as an OpenSCAD file: the holder (face numbers engraved) and the hook arm.
    Its ``faces``, ``face_mm``, ``hooks`` and ``legs`` are the data the plan is computed from."""
    faces = ",\n  ".join(f"[{n[0]:.9f}, {n[1]:.9f}, {n[2]:.9f}]" for n in fixture.normals)
    hooks = ",\n  ".join(f'["{k}", [{x:g}, {y:g}, {z:g}]]' for k, (x, y, z) in fixture.hooks_mm.items())
    legs = ",\n  ".join(f'["{k}", [{x:g}, {y:g}, {z:g}]]' for k, (x, y, z) in fixture.legs_mm.items())
    return f"""// ftsensord guided-calibration fixture (generated by `ftsensord guide --fixture`).
// Frame: the sensor's {{0}}, origin at its centre, z along the shaft towards the tip; mm.
// Print the holder and the hook arm; face k down puts gravity along faces[k-1] in {{0}}.
face_mm = {fixture.face_mm:g};   // every face's distance from the sensor's centre
bore_mm = {fixture.bore_mm:g};   // the sensor's shell sits in this bore, shaft out along +z
arm_g = {fixture.arm_g:g};        // the hook arm's mass as designed: weigh yours, pass --arm-g
arm_com_mm = [{", ".join(f"{c:g}" for c in fixture.arm_com_mm)}];
faces = [
  {faces}
];
hooks = [
  {hooks}
];
// A hook on a leg: the leg hangs from this point, the end of its branch, down to the hook.
legs = [
  {legs}
];
clamp_mm = [{", ".join(f"{c:g}" for c in CLAMP_MM)}];      // the clamp on the flange, in the bore
stem_top_mm = [{", ".join(f"{c:g}" for c in STEM_TOP_MM)}];  // the stem's top: the branches start here

function rot_to(n) = let(a = acos(n[2]), ax = norm([-n[1], n[0], 0]) < 1e-9 ? [1, 0, 0] : [-n[1], n[0], 0]) [a, ax];

module holder() {{
  difference() {{
    intersection_for(n = faces) {{
      r = rot_to(n);
      rotate(a = r[0], v = r[1]) translate([0, 0, face_mm - 200]) cube([400, 400, 400], center = true);
    }}
    cylinder(d = bore_mm, h = 4 * face_mm, center = true, $fn = 96);
    for (k = [0 : len(faces) - 1]) {{
      r = rot_to(faces[k]);
      rotate(a = r[0], v = r[1]) translate([0, 0, face_mm - 0.6])
        linear_extrude(1) text(str(k + 1), size = 6, halign = "center", valign = "center");
    }}
  }}
}}

module rod(a, b) {{ hull() {{ translate(a) sphere(d = 6, $fn = 24); translate(b) sphere(d = 6, $fn = 24); }} }}

module hook_arm() {{
  rod(clamp_mm, stem_top_mm);
  for (h = hooks) {{
    path = concat([stem_top_mm], [for (l = legs) if (l[0] == h[0]) l[1]], [h[1]]);
    for (i = [0 : len(path) - 2]) rod(path[i], path[i + 1]);
    translate(h[1]) rotate([90, 0, 0]) rotate_extrude($fn = 32) translate([4, 0]) circle(d = 2, $fn = 12);
    label = len(path) > 2 ? [8, 0, -4] : [0, 0, 6];  // beside a leg's foot, not in the leg
    translate(h[1] + label) linear_extrude(1) text(h[0], size = 5, halign = "center");
  }}
}}

holder();
translate([3 * face_mm, 0, 0]) hook_arm();
"""


def parse_openscad(
    text: str,
) -> tuple[float, np.ndarray, dict[str, np.ndarray], dict[str, np.ndarray]]:
    """``face_mm``, ``faces``, ``hooks`` and ``legs`` read back from a file `openscad` wrote."""
    import re

    face_mm = float(re.search(r"^face_mm = ([-\d.e]+);", text, re.M).group(1))  # type: ignore[union-attr]
    block = re.search(r"^faces = \[(.*?)^\];", text, re.M | re.S).group(1)  # type: ignore[union-attr]
    faces = np.array([[float(v) for v in row.split(",")] for row in re.findall(r"\[([^\[\]]+)\]", block)])

    def points(name: str) -> dict[str, np.ndarray]:
        block = re.search(rf"^{name} = \[(.*?)^\];", text, re.M | re.S).group(1)  # type: ignore[union-attr]
        return {
            k: np.array([float(v) for v in xyz.split(",")])
            for k, xyz in re.findall(r'\["(\w)", \[([^\]]+)\]\]', block)
        }

    return face_mm, faces, points("hooks"), points("legs")
