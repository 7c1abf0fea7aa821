"""The guided calibration (`ftsensord guide`): a person, masses and the printed fixture
instead of a robot (docs/guide/guided-calibration.md).

Step by step: the user is told what to do ("face 7 down, 200 g on hook E"), confirms, the
procedure waits for the silicone to settle, records the pose (`rig.record_dataset`) and checks
it against what the plan expects before it is kept:

- a bump: the pose's readings scatter far more than the chips' noise (`BUMP_FACTOR`);
- a wrong face, hook or mass: once enough loaded poses are kept, the flux's linear map to the
  wrench, H, is fitted on them (the room field's directions, measured on the no-load poses,
  projected out); a new pose's wrench as H reads it must be the plan's within a tolerance
  (`Judge.tolerance`) that grows with the step's load, as a person's honest errors and H's
  misfit do, and never reaches half-way to another step's wrench. When it is not, the
  fixture's step it looks like names the mistake ("looks like face 12 down"). The first
  poses, kept before H exists, are judged once it does, each by the others. A step read alike
  on two tries, and like no other step, is the part departing from H: kept.

A pose refused is named and the step asked again. Every pose kept is saved at once (a
dataset in the usual format, and a progress file beside it): a run stopped (a key, Ctrl-C,
``stop_after``) resumes where it stopped. At the end the dataset is fitted as `ftsensord
calibrate` does (`procedure.calibrate`) and judged on its held-out 100 g poses.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from ftsensord.calibration.dataset import POSE_FIELDS, Dataset
from ftsensord.calibration.excitation import check_excitation
from ftsensord.calibration.fixture import KIT_MASSES_G, Fixture, Step, pose_of
from ftsensord.calibration.rig import record_dataset
from ftsensord.chip import mlx90393 as mlx
from ftsensord.chip.i2c import Bus
from ftsensord.docfile import Table, load_json
from ftsensord.errors import ConfigError
from ftsensord.sim.conversion import NoiseModel
from ftsensord.sim.loads import CalibrationPose, FixedOrientation, G, Load, RecordedLoad, StaticLoad
from ftsensord.sim.person import BUMP_S, Person
from ftsensord.sim.physics import PhysicalScene

#: A pose is bumped when its readings' scatter (the RMS of its channels' standard errors) is
#: this many times the reference: the chips' own noise varies by tens of %, a knock of 1 N
#: within the reading by hundreds of times.
BUMP_FACTOR = 4.0
#: Loaded poses kept before H is fitted and the poses judged: H has 6 columns and an offset
#: per channel; with 20, a pose left out is read by H fitted on 19, nearly three times the
#: unknowns (at 14, the scatter of poses read that way hid a wrong hook under 200 g).
MIN_JUDGE_POSES = 20
#: The honest errors of a typical person's step, which no check may refuse; each scales with
#: the step's load W (N, the plan's weight on the hook arm) and its lever arm r (m):
#: a face seated off by up to this angle (rad): 3 standard deviations of the 1-2 deg a crumb
#: or a warped print gives (1.5 deg): gravity's direction off by it moves the force by W x it
#: and the torque by |r| W x it;
FACE_TILT_RAD = math.radians(4.5)
#: the masses within this share (an inexpensive hooked set's +-0.5 %, and as much again for
#: the arm weighed within 1 g of 22 on a kitchen scale);
MASS_SHARE = 0.01
#: a hook's place off by up to this (m, each axis: +-0.5 mm of a print, on three axes);
HOOK_ERROR_M = 0.5e-3 * math.sqrt(3)
#: and the chips' noise in a 100-reading mean read through H (N x3, Nm x3): a 50 g pose's
#: left-out scatter on the first 20 poses of a careful run is 0.02-0.04 N and 1-5 mNm, most
#: of it H's own misfit; this floor only covers a pose of almost no load.
NOISE_FLOOR = np.array([0.03, 0.03, 0.03, 0.002, 0.002, 0.002])
#: Or this many times the kept poses' robust scatter relative to their load (`Judge.scale`:
#: the weight for forces, the weight times the lever arm for torques), times the step's
#: load: H is linear and the part is not, so a pose's error as H reads it grows with its load
#: (a careful run of a plan with 50 g and 200 g steps: the lateral forces' left-out error over
#: its 82 loaded poses was 0.02-0.03 N RMS at 50 g and 0.14-0.15 N at 200 g); a tolerance
#: fixed in N refused correct 200 g poses while it let a 50 g slip near it pass.
SCATTER_FACTOR = 5.0
#: The tolerance reaches at most this share of the way to the nearest other step's wrench
#: (as a divisor): half-way, so a slip read with the part's misfit is still nearer what it is.
HALF_WAY = 2.0
PROGRESS_FORMAT, PROGRESS_VERSION = "ftsensord-guide-progress", 1


#: Readings of the IMU averaged per pose: its noise (6.4 mg a reading, `mpu6050.noise_g`)
#: falls to 0.9 mg, 0.05 deg of gravity's direction.
IMU_SAMPLES = 50
#: Poses the IMU's map is fitted on, at least: 12 unknowns (a 3 x 3 map and an
#: offset), 3 equations a pose; 6 poses give them 1.5 times over.
MIN_IMU_POSES = 6
#: A pose whose gravity, as the IMU reads it, is this far from the face asked for (deg) was
#: set down on another face: the holder's faces are 35 deg apart or more, a person seats one
#: within 4.5 deg, the IMU's map is good to 1 deg (0.35 deg median on a run of faces seated
#: 2 deg off).
FACE_CHECK_DEG = 15.0


class Imu(Protocol):
    """An accelerometer fixed to the holder (`chip.mpu6050.MPU6050`)."""

    def mean_accel_g(self, samples: int) -> tuple[np.ndarray, np.ndarray]: ...


@dataclass(frozen=True)
class ImuMap:
    """The IMU's reading a (g, its axes) of gravity's direction n (unit, {0}) at rest:
    a = M n + c. M takes in the sign (an accelerometer at rest reads -g), the IMU's mounting
    on the holder, its sensitivities and cross-axis terms; c its zero-g offsets. Fitted on
    the poses kept so far against their faces' normals: each face's seating error averages
    out, the more the more poses (at the end every pose is read again through the map fitted
    on all of them)."""

    M: np.ndarray
    c: np.ndarray

    @classmethod
    def fit(cls, fixture: Fixture, run: GuideRun) -> ImuMap | None:
        """From the kept steps' readings (None: fewer than `MIN_IMU_POSES`). Each
        reading's face is the one nearest to minus the reading (the IMU's axes along {0} within
        10 deg, as the guide asks, and its offsets 5 deg at most: the faces are 35 deg apart,
        17 deg half-way), so a face set down wrong does not skew the map;
        a reading far from the map the others give is left out."""
        steps = [k for k in sorted(run.accel) if k in run.kept]
        for _ in range(2):
            if len(steps) < MIN_IMU_POSES:
                return None
            a = np.array([run.accel[k] for k in steps])
            n = fixture.normals[np.argmax(-a @ fixture.normals.T, axis=1)]
            coef, *_ = np.linalg.lstsq(np.column_stack([n, np.ones(len(n))]), a, rcond=None)
            found = cls(coef[:3].T, coef[3])
            off = [found.angle_deg(found.gravity(run.accel[k]), n[i]) for i, k in enumerate(steps)]
            if max(off) <= FACE_CHECK_DEG:
                return found
            steps = [k for k, o in zip(steps, off) if o <= FACE_CHECK_DEG]
        return found if len(steps) >= MIN_IMU_POSES else None

    def gravity(self, accel: np.ndarray) -> np.ndarray:
        """Gravity's direction in {0} (unit) from a reading (g)."""
        n = np.linalg.solve(self.M, np.asarray(accel) - self.c)
        return np.asarray(n / np.linalg.norm(n))

    @staticmethod
    def angle_deg(u: np.ndarray, v: np.ndarray) -> float:
        return float(np.degrees(np.arccos(np.clip(float(u @ v), -1.0, 1.0))))

    def check(self, fixture: Fixture, step: Step, gravity: np.ndarray) -> str | None:
        """Why the pose is on another face than ``step``'s, or None."""
        off = self.angle_deg(gravity, fixture.normals[step.face - 1])
        if off <= FACE_CHECK_DEG:
            return None
        nearest = int(np.argmax(fixture.normals @ gravity)) + 1
        return (
            f"the IMU reads gravity {off:.0f} deg from face {step.face}'s direction; it looks like face "
            f"{nearest} down, not face {step.face}: a wrong face"
        )


class Stop(Exception):
    """The user stopped the run (what was kept is saved)."""


class Station(Protocol):
    """Who carries the steps out: a person at a real sensor, or the simulator's."""

    def perform(self, index: int, attempt: int, step: Step, reading_at_s: float, reading_s: float) -> None:
        """Carry step ``index`` out (its ``attempt``-th try); the reading starts at the bus's
        ``reading_at_s`` and lasts about ``reading_s``."""
        ...


class Prompter(Protocol):
    def say(self, line: str) -> None: ...

    def confirm(self, line: str) -> None:
        """Ask for the step to be done; raise `Stop` when the user stops."""
        ...


@dataclass
class GuideRun:
    """The state of a run: the poses kept (by step), each step's attempts, what was refused."""

    steps: list[Step]
    kept: dict[int, Dataset] = field(default_factory=dict)
    attempts: dict[int, int] = field(default_factory=dict)
    refused: list[str] = field(default_factory=list)
    #: Each refusal as (step, attempt refused): a pose refused at once, or kept and refused
    #: later when all were judged again (what a benchmark matches against the slips made).
    refusals: list[tuple[int, int]] = field(default_factory=list)
    #: Steps read alike on two tries after a refusal: the part, not a slip (kept from then on).
    confirmed: set[int] = field(default_factory=set)
    #: The IMU's mean reading (g, its axes) at each step's last try: what its map is fitted on.
    accel: dict[int, np.ndarray] = field(default_factory=dict)
    elapsed_s: float = 0.0  # the bus's time over earlier sessions

    def dataset(self, serial: str = "", source: str = "") -> Dataset:
        return concat([self.kept[k] for k in sorted(self.kept)], serial, source)


def concat(parts: Sequence[Dataset], serial: str = "", source: str = "") -> Dataset:
    """One dataset of single poses, in the plan's order (no rotations: a person does not know the
    turn about the vertical, the room's field is measured from the no-load poses instead; no
    times: a step done again is read later than the steps after it, out of the file's order)."""
    first = parts[0]
    arrays: dict[str, Any] = {name: np.concatenate([getattr(p, name) for p in parts]) for name in POSE_FIELDS}
    known = [p.temperature_c for p in parts if p.temperature_c is not None]
    temps = np.concatenate(known) if len(known) == len(parts) else None
    return replace(
        first,
        **arrays,
        rotation=None,
        times_s=None,
        temperature_c=temps,
        serial=serial or first.serial,
        source=source or first.source,
    )


def expected_sem_t(samples: int, settings: mlx.Settings = mlx.Settings()) -> float:
    """The chips' noise (T, RMS over axes) in a pose's mean of ``samples`` readings: the datasheet's."""
    sigma = [NoiseModel().sigma_ut(a, settings.tconvm_us()) for a in "xyz"]
    return float(np.sqrt(np.mean(np.square(sigma)))) * 1e-6 / math.sqrt(samples)


class Judge:
    """The checks a pose must pass before it is kept."""

    def __init__(self, fixture: Fixture, samples: int):
        self.fixture = fixture
        self.reference_sem = expected_sem_t(samples)
        candidates = [(0, 0.0, "-")] + [
            (f, m, h)
            for f in range(1, len(fixture.normals) + 1)
            for m in (*KIT_MASSES_G, 0.0)
            for h in fixture.hooks_mm
        ]
        self.candidates = candidates
        self.candidate_w = np.array(
            [np.zeros(6) if f == 0 else pose_of(fixture, f, m, h).wrench() for f, m, h in candidates]
        )

    def bump(self, pose: Dataset, kept: Sequence[Dataset]) -> str | None:
        sem = float(np.sqrt(np.mean(pose.flux_sem_t**2)))
        others = [float(np.sqrt(np.mean(p.flux_sem_t**2))) for p in kept]
        # The kept poses' median once there are a few (the chips as they are), else the datasheet's.
        reference = float(np.median(others)) if len(others) >= 5 else self.reference_sem
        if sem > BUMP_FACTOR * reference:
            return (
                f"the readings scattered {sem / reference:.0f} times as much as the chips' noise: "
                "the sensor moved or was bumped while it was read"
            )
        return None

    @staticmethod
    def _room(no_load: Sequence[Dataset]) -> tuple[np.ndarray, np.ndarray]:
        """The no-load poses' mean flux and the projection that takes the room's 3 directions out."""
        flux = np.concatenate([p.flux_t for p in no_load])
        mean = flux.mean(axis=0)
        _, _, vt = np.linalg.svd(flux - mean, full_matrices=False)
        room = vt[:3].T if len(flux) >= 4 else np.zeros((flux.shape[1], 0))
        return mean, np.eye(flux.shape[1]) - room @ room.T

    def read(
        self, loaded: Sequence[Dataset], no_load: Sequence[Dataset], new: Sequence[Dataset]
    ) -> np.ndarray:
        """The wrenches H, fitted on ``loaded``, reads in ``new`` (n, 6)."""
        b0, P = self._room(no_load)
        B = np.concatenate([p.flux_t for p in loaded]) - b0
        W = np.concatenate([p.wrench for p in loaded])
        X = np.column_stack([W, np.ones(len(W))])
        coef, *_ = np.linalg.lstsq(X, B @ P, rcond=None)  # B P = [W 1] coef
        H, c = coef[:6].T, coef[6]
        Bn = np.concatenate([p.flux_t for p in new]) - b0
        w, *_ = np.linalg.lstsq(H, ((Bn @ P) - c).T, rcond=None)
        return np.asarray(w.T)

    def left_out(self, loaded: Sequence[Dataset], no_load: Sequence[Dataset]) -> np.ndarray:
        """Each kept loaded pose's residual as H fitted on the others reads it (n, 6): what a new
        pose's error is like, where the poses' own residuals would understate it."""
        return np.array(
            [
                self.read([p for j, p in enumerate(loaded) if j != i], no_load, [q])[0] - q.wrench[0]
                for i, q in enumerate(loaded)
            ]
        )

    def can_judge(self, loaded: Sequence[Dataset], no_load: Sequence[Dataset]) -> bool:
        if len(loaded) < MIN_JUDGE_POSES or len(no_load) < 4:
            return False
        return check_excitation(np.concatenate([p.wrench for p in loaded])).identifiable

    def scale(self, step: Step) -> np.ndarray:
        """The size of ``step``'s load (N x3, Nm x3): its weight W on the hook arm, and W times
        its lever arm |r| (the torque it makes with gravity square to the arm)."""
        pose = pose_of(self.fixture, step.face, step.mass_g, step.hook)
        weight = pose.mass_kg * G
        return np.r_[np.full(3, weight), np.full(3, weight * float(np.linalg.norm(pose.lever_m)))]

    def honest(self, step: Step) -> np.ndarray:
        """How far a typical person's correct ``step`` is off the plan's wrench, at most (N x3, Nm x3)."""
        load = self.scale(step)
        weight = load[0]
        off = np.r_[load[:3], load[3:]] * (FACE_TILT_RAD + MASS_SHARE)
        return NOISE_FLOOR + off + np.r_[np.zeros(3), np.full(3, weight * HOOK_ERROR_M)]

    def tolerance(self, residuals: np.ndarray, kept: Sequence[Step], step: Step) -> np.ndarray:
        """The largest error (N x3, Nm x3) a correct ``step`` is read with: its honest errors, or
        `SCATTER_FACTOR` times the ``kept`` poses' left-out ``residuals`` relative to their
        load (`scale`), at this step's load."""
        if len(residuals):
            loads = np.array([self.scale(k) for k in kept])
            relative = 1.4826 * np.median(np.abs(residuals) / loads, axis=0)
        else:
            relative = np.zeros(6)
        honest = self.honest(step)
        tol = np.maximum(honest, SCATTER_FACTOR * relative * self.scale(step))
        # Never half-way to another step of the fixture (any face, mass or hook): a slip's
        # reading stays nearer the wrench it is than the plan's. Steps an honest error cannot
        # tell from the plan's (two hooks on one vertical line) are the same pose.
        change = np.abs(self.candidate_w - pose_of(self.fixture, step.face, step.mass_g, step.hook).wrench())
        other = np.max(change / honest, axis=1) > 1.0
        if other.any():
            reach = float(np.min(np.max(change[other] / tol, axis=1)))
            tol = np.maximum(honest, tol * min(1.0, reach / HALF_WAY))
        return tol

    def looks_like_plan(self, step: Step, read: np.ndarray, tolerance: np.ndarray) -> bool:
        """Is ``read`` nearer ``step``'s wrench than any other step's of the fixture (in
        ``tolerance`` units)? Other steps an honest error cannot tell from it do not count."""
        plan = pose_of(self.fixture, step.face, step.mass_g, step.hook).wrench()
        same = np.max(np.abs(self.candidate_w - plan) / self.honest(step), axis=1) <= 1.0
        distance = np.max(np.abs(self.candidate_w - read) / tolerance, axis=1)
        return bool(np.max(np.abs(read - plan) / tolerance) < np.min(distance[~same], initial=np.inf))

    def name(self, step: Step, read: np.ndarray, tolerance: np.ndarray) -> str:
        """What the reading looks like, in the fixture's steps: the mistake named."""
        k = int(np.argmin(np.max(np.abs(self.candidate_w - read) / tolerance, axis=1)))
        face, mass, hook = self.candidates[k]
        off = np.abs(read - pose_of(self.fixture, step.face, step.mass_g, step.hook).wrench()) / tolerance
        axis = ["Fx", "Fy", "Fz", "Mx", "My", "Mz"][int(np.argmax(off))]
        said = f"{axis} {off.max():.1f} times the tolerance off the plan's wrench"
        if face == 0 or mass == 0.0:
            return f"{said}; it looks like no mass on the hook: is the {step.mass_g:g} g mass hanging?"
        if face != step.face:
            return f"{said}; it looks like face {face} down, not face {step.face}: a wrong face"
        if hook != step.hook:
            return f"{said}; it looks like the mass on hook {hook}, not hook {step.hook}: a wrong hook"
        if mass != step.mass_g:
            return f"{said}; it looks like {mass:g} g, not {step.mass_g:g} g: a wrong mass"
        return f"{said}; check the face sits flat and the mass hangs free"


def judge_all(judge: Judge, run: GuideRun) -> list[tuple[int, str, np.ndarray]]:
    """The kept loaded poses judged each by the others, one at a time (of those off the plan,
    the one whose leaving out explains the rest best): a wrong one skews H for the rest until it
    is out; a step read alike twice (`GuideRun.confirmed`) helps
    judge the others but is not refused again. Returns the refused steps, why, and each one's
    wrench as H read it."""
    loaded = [k for k in sorted(run.kept) if run.steps[k].split != "no-load"]
    no_load = [run.kept[k] for k in sorted(run.kept) if run.steps[k].split == "no-load"]
    out: list[tuple[int, str, np.ndarray]] = []
    while len(loaded) > MIN_JUDGE_POSES // 2:
        res = []
        for k in loaded:
            others = [run.kept[j] for j in loaded if j != k]
            res.append(judge.read(others, no_load, [run.kept[k]])[0] - run.kept[k].wrench[0])
        r = np.array(res)
        kept = [run.steps[k] for k in loaded]
        tol = np.array([judge.tolerance(r, kept, run.steps[k]) for k in loaded])
        off = np.max(np.abs(r) / tol, axis=1)
        off[[k in run.confirmed for k in loaded]] = 0.0
        suspects = np.flatnonzero(off > 1.0)
        if not len(suspects):
            break
        # The suspect whose leaving out explains the others best: a slip skews H, and the
        # correct poses H then misreads can look worse, as read left out, than the slip itself
        # (a missing 200 g among the first 20 poses made five correct ones look 8-12 times off).
        score = []
        for i in suspects:
            rest = [run.kept[j] for j in loaded if j != loaded[i]]
            e = judge.read(rest, no_load, rest) - np.concatenate([p.wrench for p in rest])
            score.append(float(np.max(np.abs(e) / np.delete(tol, i, axis=0))))
        worst = int(suspects[int(np.argmin(score))])
        k = loaded.pop(worst)
        read = r[worst] + run.kept[k].wrench[0]
        out.append((k, judge.name(run.steps[k], read, tol[worst]), read))
    return out


def progress_bar(done: int, total: int, width: int = 30) -> str:
    full = round(width * done / total) if total else width
    return f"[{'#' * full}{'.' * (width - full)}] {done}/{total}"


def record_pose(
    bus: Bus,
    addresses: Sequence[int],
    fixture: Fixture,
    step: Step,
    samples: int,
    offset_s: float,
    gravity: np.ndarray | None = None,
) -> Dataset:
    """One pose of the plan read (`rig.record_dataset`), its times on the run's clock; its
    wrench with ``gravity`` (unit, {0}: the IMU's) when given, else the face's."""
    pose = pose_of(
        fixture, step.face, step.mass_g, step.hook, arm_on=step.split != "no-load", gravity=gravity
    )
    ds = record_dataset(bus, addresses, [(pose, step.split)], lambda w: None, samples=samples)
    assert ds.times_s is not None  # (record_dataset stamps every pose)
    return replace(ds, times_s=ds.times_s + offset_s, rotation=None)


def guide(
    run: GuideRun,
    *,
    bus: Bus,
    addresses: Sequence[int],
    fixture: Fixture,
    station: Station,
    prompter: Prompter,
    samples: int,
    settle_s: float,
    save: Callable[[GuideRun], None],
    stop_after: int | None = None,
    imu: Imu | None = None,
) -> bool:
    """Take the run's steps not yet kept, in order, each until it is kept. Returns True when
    every step is kept, False when stopped (``stop_after`` poses recorded in this session, or
    the user): what was kept is saved after every pose."""
    judge = Judge(fixture, samples)
    start = bus.monotonic()
    recorded = 0
    judged_at = 0  # how many loaded poses were kept when all were last judged (0: not yet)
    queue = [k for k in range(len(run.steps)) if k not in run.kept]
    reads: dict[int, np.ndarray] = {}  # each refused step's last reading, as H read it
    reading_s = 0.01 * samples  # until the first pose says how long a reading takes
    while queue:
        k = queue[0]
        step = run.steps[k]
        if stop_after is not None and recorded >= stop_after:
            return False
        attempt = run.attempts.get(k, 0)
        run.attempts[k] = attempt + 1
        prompter.say(f"{progress_bar(len(run.kept), len(run.steps))}  step {k + 1}: {step.instruction()}")
        prompter.confirm(step.instruction())
        begin = bus.monotonic()
        station.perform(k, attempt, step, begin + settle_s, reading_s)
        if settle_s > 0:
            prompter.say(f"  waiting {settle_s:.0f} s for the silicone to settle")
            bus.sleep(settle_s)
        gravity, imu_why = None, None
        if imu is not None:
            accel, _ = imu.mean_accel_g(IMU_SAMPLES)
            run.accel[k] = accel  # with the pose, once kept: the IMU's map is fitted on these
            imu_map = ImuMap.fit(fixture, run) if step.split != "no-load" else None
            if imu_map is not None:
                gravity = imu_map.gravity(accel)
                imu_why = imu_map.check(fixture, step, gravity)
        pose = record_pose(bus, addresses, fixture, step, samples, run.elapsed_s + begin - start, gravity)
        reading_s = bus.monotonic() - begin - settle_s
        recorded += 1
        kept = [run.kept[j] for j in sorted(run.kept)]
        why = judge.bump(pose, kept) or imu_why
        loaded = [run.kept[j] for j in sorted(run.kept) if run.steps[j].split != "no-load"]
        no_load = [run.kept[j] for j in sorted(run.kept) if run.steps[j].split == "no-load"]
        if why is None and step.split != "no-load" and judged_at:
            read = judge.read(loaded, no_load, [pose])[0]
            kept_steps = [run.steps[j] for j in sorted(run.kept) if run.steps[j].split != "no-load"]
            tol = judge.tolerance(judge.left_out(loaded, no_load), kept_steps, step)
            before = reads.get(k)
            alike = before is not None and np.max(np.abs(read - before) / tol) <= 1.0
            if np.max(np.abs(read - pose.wrench[0]) / tol) > 1.0:
                reads[k] = read
                if not alike or not judge.looks_like_plan(step, read, tol):
                    why = judge.name(step, read, tol)
                else:  # read alike twice, and like no other step: the part departs from H, no slip
                    run.confirmed.add(k)
                    prompter.say(
                        "  the same reading as the last try: kept (the part departs from the early fit)"
                    )
            elif alike:  # refused when all were judged, read alike again: not to be refused again
                run.confirmed.add(k)
        if why is not None:
            run.refused.append(f"step {k + 1} ({step.instruction()}): {why}")
            run.refusals.append((k, attempt))
            prompter.say(f"  REDO: {why}")
            save(run)
            continue
        run.kept[k] = pose
        queue.pop(0)
        prompter.say("  kept")
        loaded = [run.kept[j] for j in sorted(run.kept) if run.steps[j].split != "no-load"]
        # Every kept pose judged by the others when H first can be, again each time the poses
        # double (an early H, on few poses, misses what a later one sees), and at the end.
        again = judge.can_judge(loaded, no_load) and (len(loaded) >= 2 * judged_at or not queue[0:1])
        if again and len(loaded) > judged_at:
            judged_at = len(loaded)
            for j, why, read in judge_all(judge, run):
                reads[j] = read  # the step done again and read alike is kept
                del run.kept[j]
                queue.insert(0, j)
                run.refusals.append((j, run.attempts[j] - 1))
                run.refused.append(f"step {j + 1} ({run.steps[j].instruction()}): {why}")
                prompter.say(f"  step {j + 1} again: {why}")
        save(run)
    final = ImuMap.fit(fixture, run) if imu is not None else None
    if final is not None:  # every pose's gravity again, through the map fitted on all of them
        regravitate(run, fixture, final)
        save(run)
    prompter.say(progress_bar(len(run.kept), len(run.steps)))
    return True


def regravitate(run: GuideRun, fixture: Fixture, imu_map: ImuMap) -> None:
    """Each kept loaded pose's gravity (and so its wrench) as ``imu_map`` reads its IMU reading."""
    for k in sorted(run.kept):
        step = run.steps[k]
        if step.split == "no-load" or k not in run.accel:
            continue
        g = imu_map.gravity(run.accel[k])
        pose = pose_of(fixture, step.face, step.mass_g, step.hook, gravity=g)
        run.kept[k] = replace(run.kept[k], gravity_dir=g[None, :], wrench=pose.wrench()[None, :])


def save_run(run: GuideRun, progress: Path, partial: Path, serial: str, source: str) -> None:
    """The progress file (the plan's steps, those kept, what was refused) and the kept poses
    as a dataset (`ftsensord calibrate` reads it too)."""
    if run.kept:
        run.dataset(serial, source).save(partial)
    doc = {
        "format": PROGRESS_FORMAT,
        "version": PROGRESS_VERSION,
        "plan": [s.instruction() + f" ({s.split})" for s in run.steps],
        "kept": sorted(run.kept),
        "attempts": {str(k): v for k, v in sorted(run.attempts.items())},
        "refused": run.refused,
        "confirmed": sorted(run.confirmed),
        "accel": {str(k): [float(x) for x in v] for k, v in sorted(run.accel.items())},
        "dataset": partial.name,
    }
    progress.write_text(json.dumps(doc, indent=1) + "\n")


def load_run(steps: list[Step], progress: Path, partial: Path) -> GuideRun:
    """A stopped run, to resume; its plan must be this one (errors name the file and key)."""
    doc = Table(load_json(progress), progress)
    doc.only({"format", "version", "plan", "kept", "attempts", "refused", "confirmed", "accel", "dataset"})
    if doc.get("format") != PROGRESS_FORMAT:
        raise doc.fail("format", f'"{PROGRESS_FORMAT}"', doc.get("format"))
    doc.integer("version", what=str(PROGRESS_VERSION), low=PROGRESS_VERSION, high=PROGRESS_VERSION)
    plan = [s.instruction() + f" ({s.split})" for s in steps]
    if doc.get("plan") != plan:
        raise doc.fail(
            "plan", "the plan this run asks for (same fixture and options), or --restart", "another plan"
        )
    kept = doc.get("kept")
    if not isinstance(kept, list) or not all(isinstance(k, int) and 0 <= k < len(steps) for k in kept):
        raise doc.fail("kept", f"step indices in 0-{len(steps) - 1}", kept)
    run = GuideRun(steps)
    if kept:
        data = Dataset.load(partial)
        if len(data) != len(kept):
            raise ConfigError(
                f"{partial}: poses: expected {len(kept)} (the progress file's kept steps), got {len(data)}"
            )
        for i, k in enumerate(sorted(kept)):
            run.kept[k] = data.select(np.arange(len(data)) == i)
    attempts = doc.get("attempts", {})
    run.attempts = {int(k): int(v) for k, v in attempts.items()} if isinstance(attempts, dict) else {}
    refused = doc.get("refused", [])
    run.refused = [str(r) for r in refused] if isinstance(refused, list) else []
    confirmed = doc.get("confirmed", [])
    run.confirmed = {int(k) for k in confirmed} if isinstance(confirmed, list) else set()
    accel = doc.get("accel", {})
    run.accel = (
        {int(k): np.array(v, dtype=float) for k, v in accel.items()} if isinstance(accel, dict) else {}
    )
    return run


class SimStation:
    """The simulator's person (`sim.person`) at a scene's sensor: each step done as told, with
    the person's errors; ``slips`` lists every mistake made (step, attempt, what)."""

    def __init__(self, scene: PhysicalScene, sensor: str, fixture: Fixture, person: Person):
        self.scene, self.sensor, self.fixture, self.person = scene, sensor, fixture, person
        self.slips: list[tuple[int, int, str]] = []

    def perform(self, index: int, attempt: int, step: Step, reading_at_s: float, reading_s: float) -> None:
        f, person = self.fixture, self.person
        act = person.act(index, attempt, step.face, step.mass_g, step.hook, f.normals, list(f.hooks_mm))
        slips = [s for s in act.slips if step.split != "no-load" or s == "a bump"]  # no arm: the face is free
        self.slips += [(index, attempt, s) for s in slips]
        w = np.zeros(6)
        if step.split != "no-load":
            arm = (f.arm_g + person.mass_error("arm")) * 1e-3
            m = act.mass_g * (1 + person.mass_error(f"{act.mass_g:g} g")) * 1e-3
            hook = (np.array(f.hooks_mm[act.hook]) + person.hook_error_mm(act.hook)) * 1e-3
            lever = (m * hook + arm * np.array(f.arm_com_mm) * 1e-3) / (m + arm)
            w = CalibrationPose(act.gravity, m + arm, lever).wrench()
        load: Load = StaticLoad(w)
        if act.bump is not None:
            at = reading_at_s + act.bump[0] * reading_s
            knock = np.concatenate([act.bump[1], np.zeros(3)])
            load = RecordedLoad(
                np.array([0.0, at, at + 1e-3, at + BUMP_S, at + BUMP_S + 1e-3]),
                np.array([w, w, w + knock, w + knock, w]),
            )
        self.scene.set_orientation(self.sensor, FixedOrientation(act.rotation))
        self.scene.set_load(self.sensor, load)
