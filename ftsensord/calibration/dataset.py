"""Calibration datasets: what a calibration run records, simulated or real.

One JSON document (format in docs/guide/calibration.md): per pose, the applied
wrench in the sensor frame {0} (N, Nm), the flux of each chip averaged over
``samples_per_pose`` readings (T, chip frames, stacked chip by chip), the
standard error of each mean, which chips saturated, and how the pose was made
(mass, lever arm, gravity's direction). Optionally, per chip, a position-map
sweep (the paper's stage experiment): magnet positions (m, chip frame) and the
flux read at each. Optionally, per pose, the sensor's full orientation in the
world (``rotation``, R_w0), which a robot knows from its joints.

Flux that no MLX90393 can report is refused when a dataset is read or fitted
(`implausible_flux`): a chip's Hall element saturates near 50 mT whatever its
gain, so a larger value is a unit error (mT, uT or gauss written as T) or garbage.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from ftsensord.chip import mlx90393 as mlx
from ftsensord.docfile import Table, load_json

DATASET_FORMAT = "ftsensord-calibration-dataset"
DATASET_VERSION = 1
UNITS = {"flux": "T", "wrench": "N, Nm", "length": "m", "mass": "kg"}
#: "no-load": the sensor alone (rod and mass off) at an orientation: what the room's field
#: does to the chips; "check": a large load (kilograms at the flange's centre), fitted on by
#: nothing, on which the flux model is judged beyond the fit's loads (docs/guide/calibration.md).
SPLITS = ("fit", "validation", "no-load", "check")
#: The wrench's axes and their units, in the order of ``wrench``.
AXES = ("Fx", "Fy", "Fz", "Mx", "My", "Mz")
AXIS_UNITS = ("N", "N", "N", "Nm", "Nm", "Nm")
#: The per-pose arrays of a `Dataset`, as named in the file's "poses" entries.
POSE_FIELDS = ("split", "mass_kg", "lever_m", "gravity_dir", "wrench", "flux_t", "flux_sem_t", "saturated")
#: The largest |flux| a chip's reading can have (T): its Hall element saturates at 50 mT
#: whatever the gain, and the mean of clipped readings stays there; plus 10 uT, about one
#: LSB of the widest setting (9.7 uT on Z), for the quantisation of a clipped reading.
FLUX_LIMIT_T = mlx.HALL_SATURATION_T + 10e-6
#: Units a wrong flux is commonly written in, and their size in T, for the refusal's hint.
WRONG_UNITS = (("mT", 1e-3), ("gauss", 1e-4), ("uT", 1e-6))
#: A unit is suggested only if the strongest reading it gives is at least this (T): each
#: chip has its magnet 6 mm away, about 1.5 mT, so a sensor's strongest reading is never
#: below 0.1 mT (the magnet would have to be 15 mm off).
STRONGEST_READING_MIN_T = 1e-4


def implausible_flux(values: ArrayLike, saturated: ArrayLike | None = None) -> str | None:
    """Why ``values`` (T) cannot be a chip's readings, or None when they can. The
    channels of chips flagged ``saturated`` (one bool per chip, per row) are not
    readings and not judged: whatever a clipped chip reports is left out anyway."""
    values = np.asarray(values, dtype=float)
    if saturated is not None:
        values = np.where(np.repeat(np.asarray(saturated, dtype=bool), 3, axis=-1), 0.0, values)
    if not values.size:
        return None
    worst = float(np.abs(values).max())
    if worst <= FLUX_LIMIT_T:
        return None
    units = [
        f"{unit} (x {size:g})"
        for unit, size in WRONG_UNITS
        if STRONGEST_READING_MIN_T <= worst * size <= FLUX_LIMIT_T
    ]
    hint = f"; it would fit if written in {' or '.join(units)}" if units else ""
    return (
        f"|flux| up to {worst:.4g} T, beyond the {mlx.HALL_SATURATION_T * 1e3:g} mT an MLX90393 can "
        f"read (flux is in T){hint}"
    )


@dataclass
class Sweep:
    """A position-map sweep for one chip: ``position_m`` (k, 3) and ``flux_t`` (k, 3)."""

    position_m: np.ndarray
    flux_t: np.ndarray


@dataclass
class Hold:
    """A step-and-hold segment (`rig.record_hold`): the loads the robot applied, each from
    ``load_times_s`` (s) on (``loads``, (k, 6) N, Nm in {0}), and every reading in between:
    ``times_s`` (m,) and ``flux_t`` (m, 3 * chips) T. What the silicone's relaxation is
    identified from (`calibration.relaxation`)."""

    load_times_s: np.ndarray
    loads: np.ndarray
    times_s: np.ndarray
    flux_t: np.ndarray

    def document(self) -> dict:
        return {
            "load_times_s": self.load_times_s.tolist(),
            "loads": self.loads.tolist(),
            "times_s": self.times_s.tolist(),
            "flux_t": self.flux_t.tolist(),
        }

    @classmethod
    def parse(cls, t: Table, channels: int) -> Hold:
        t.only({"load_times_s", "loads", "times_s", "flux_t"})
        load_times = np.array(t.numbers("load_times_s", unit="s"))
        times = np.array(t.numbers("times_s", unit="s"))
        for key, v in (("load_times_s", load_times), ("times_s", times)):
            if len(v) < 2 or np.any(np.diff(v) <= 0):
                raise t.fail(key, "at least two strictly increasing times (s)", v.tolist())
        if times[0] < load_times[0]:
            raise t.fail("times_s", f"readings from the first load's time on ({load_times[0]} s)", times[0])
        if load_times[-1] >= times[-1]:  # a load no reading saw: a log cut short, or the wrong clock
            raise t.fail(
                "load_times_s", f"loads applied before the last reading ({times[-1]} s)", load_times[-1]
            )
        flux = np.array(t.matrix("flux_t", len(times), channels, unit="T"))
        why = implausible_flux(flux)
        if why is not None:
            raise t.fail("flux_t", f"readings an MLX90393 can make: {why}", "out of range")
        return cls(load_times, np.array(t.matrix("loads", len(load_times), 6, unit="N, Nm")), times, flux)


@dataclass
class Dataset:
    """n poses of one sensor of ``len(addresses)`` chips (arrays indexed by pose)."""

    addresses: tuple[int, ...]
    wrench: np.ndarray  # (n, 6) N, Nm in {0}
    flux_t: np.ndarray  # (n, 3 * chips) T
    flux_sem_t: np.ndarray  # (n, 3 * chips) T, standard error of each mean
    saturated: np.ndarray  # (n, chips) bool
    split: np.ndarray  # (n,) "fit" or "validation"
    mass_kg: np.ndarray  # (n,)
    lever_m: np.ndarray  # (n, 3)
    gravity_dir: np.ndarray  # (n, 3)
    samples_per_pose: int = 1
    serial: str = ""
    source: str = ""
    sweeps: dict[int, Sweep] = field(default_factory=dict)
    rotation: np.ndarray | None = None  # (n, 3, 3) R_w0 per pose, world z up; None: not recorded
    temperature_c: np.ndarray | None = (
        None  # (n,) the chips' mean die temperature per pose, degC; None: not recorded
    )
    hold: Hold | None = None  # the step-and-hold segment; None: not recorded
    #: (n, 3) s on one clock through the run: when each pose's load was applied, and its first
    #: and last reading (the silicone's creep in each dwell, `creep.dwell_loads`); None: not recorded.
    times_s: np.ndarray | None = None
    path: str = ""  # the file it was read from, for error messages (not saved)

    def __len__(self) -> int:
        return len(self.wrench)

    def select(self, mask: np.ndarray) -> Dataset:
        """The poses where ``mask`` is true (sweeps kept)."""
        picked = {name: getattr(self, name)[mask] for name in POSE_FIELDS}
        return replace(
            self,
            **picked,
            rotation=None if self.rotation is None else self.rotation[mask],
            temperature_c=None if self.temperature_c is None else self.temperature_c[mask],
            times_s=None if self.times_s is None else self.times_s[mask],
        )

    def temperature_range(self) -> tuple[float, float, float] | None:
        """The die temperature over the poses (degC): mean, lowest, highest; None: not recorded."""
        t = self.temperature_c
        return None if t is None or not len(t) else (float(t.mean()), float(t.min()), float(t.max()))

    def where(self) -> str:
        """'ds.json: ' when read from a file, for messages that name it."""
        return f"{self.path}: " if self.path else ""

    def save(self, path: str | Path) -> None:
        doc = {
            "format": DATASET_FORMAT,
            "version": DATASET_VERSION,
            "units": dict(UNITS),
            "frame": "sensor frame {0}: origin at the sensor's centre, z along the shaft towards the tip",
            "sensor": {"serial": self.serial, "addresses": [f"0x{a:02X}" for a in self.addresses]},
            "samples_per_pose": self.samples_per_pose,
            "source": self.source,
            "poses": [
                {
                    "split": str(self.split[k]),
                    "mass_kg": float(self.mass_kg[k]),
                    "lever_m": self.lever_m[k].tolist(),
                    "gravity_dir": self.gravity_dir[k].tolist(),
                    "wrench": self.wrench[k].tolist(),
                    "flux_t": self.flux_t[k].tolist(),
                    "flux_sem_t": self.flux_sem_t[k].tolist(),
                    "saturated": self.saturated[k].tolist(),
                    **({} if self.rotation is None else {"rotation": self.rotation[k].tolist()}),
                    **({} if self.temperature_c is None else {"temperature_c": float(self.temperature_c[k])}),
                    **({} if self.times_s is None else {"times_s": self.times_s[k].tolist()}),
                }
                for k in range(len(self))
            ],
            "position_sweeps": {
                f"0x{a:02X}": {"position_m": s.position_m.tolist(), "flux_t": s.flux_t.tolist()}
                for a, s in self.sweeps.items()
            },
            **({} if self.hold is None else {"hold": self.hold.document()}),
        }
        Path(path).write_text(json.dumps(doc, indent=1) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> Dataset:
        """Read and validate a dataset; errors name the file, the key and what was expected."""
        doc = Table(load_json(path), path)
        doc.only(
            {
                "format",
                "version",
                "units",
                "frame",
                "sensor",
                "samples_per_pose",
                "source",
                "poses",
                "position_sweeps",
                "hold",
            }
        )
        if doc.get("format") != DATASET_FORMAT:
            raise doc.fail("format", f'"{DATASET_FORMAT}"', doc.get("format"))
        doc.integer("version", what=f"{DATASET_VERSION}", low=DATASET_VERSION, high=DATASET_VERSION)
        if doc.get("units") != UNITS:
            raise doc.fail("units", str(UNITS), doc.get("units"))
        sensor = doc.table("sensor")
        sensor.only({"serial", "addresses"})
        addresses = parse_addresses(sensor, "addresses")
        chips = len(addresses)
        columns: dict[str, list] = {name: [] for name in POSE_FIELDS}
        rotations: list[np.ndarray] = []
        temperatures: list[float] = []
        times: list[list[float]] = []
        rows = doc.tables("poses")
        for row in rows:
            row.only((*POSE_FIELDS, "rotation", "temperature_c", "times_s"))
            sat = row.get("saturated")
            if not isinstance(sat, list) or len(sat) != chips or not all(isinstance(v, bool) for v in sat):
                raise row.fail("saturated", f"{chips} booleans, one per chip", sat)
            columns["saturated"].append(sat)
            columns["split"].append(row.string("split", choices=SPLITS))
            columns["mass_kg"].append(row.number("mass_kg", low=0, unit="kg"))
            columns["lever_m"].append(row.numbers("lever_m", 3, unit="m"))
            columns["gravity_dir"].append(row.numbers("gravity_dir", 3))
            columns["wrench"].append(row.numbers("wrench", 6, unit="N, Nm"))
            for key in ("flux_t", "flux_sem_t"):
                values = row.numbers(key, 3 * chips, unit="T")
                why = implausible_flux(values, sat)
                if why is not None:
                    raise row.fail(key, f"{3 * chips} readings an MLX90393 can make: {why}", values)
                columns[key].append(values)
            if any(v < 0 for v in columns["flux_sem_t"][-1]):
                raise row.fail("flux_sem_t", "standard errors >= 0 (T)", columns["flux_sem_t"][-1])
            if ("rotation" in row.doc) != ("rotation" in rows[0].doc):
                raise row.fail(
                    "rotation",
                    "a rotation in every pose or in none (as poses[0])",
                    row.doc.get("rotation", "none"),
                )
            if "rotation" in row.doc:
                rotations.append(_rotation(row, columns["gravity_dir"][-1]))
            if ("temperature_c" in row.doc) != ("temperature_c" in rows[0].doc):
                raise row.fail(
                    "temperature_c",
                    "a temperature in every pose or in none (as poses[0])",
                    row.doc.get("temperature_c", "none"),
                )
            if "temperature_c" in row.doc:  # the chips' operating range, as a scene's
                low, high = mlx.OPERATING_RANGE_C
                temperatures.append(row.number("temperature_c", low=low, high=high, unit="degC"))
            if ("times_s" in row.doc) != ("times_s" in rows[0].doc):
                raise row.fail(
                    "times_s", "times in every pose or in none (as poses[0])", row.doc.get("times_s", "none")
                )
            if "times_s" in row.doc:
                times.append(_times(row, times[-1][2] if times else -np.inf))
        sweeps = {}
        if "position_sweeps" in doc.doc:
            table = doc.table("position_sweeps")
            for key in table.doc:
                address = parse_address(table, key, key)
                if address not in addresses:
                    raise table.fail(key, f"one of the sensor's addresses {sensor.get('addresses')}", key)
                s = table.table(key)
                s.only({"position_m", "flux_t"})
                positions = s.get("position_m")
                if not isinstance(positions, list):  # its length sizes both matrices
                    raise s.fail("position_m", "a list of magnet positions [x, y, z] (m)", positions)
                k = len(positions)
                flux = np.array(s.matrix("flux_t", k, 3, unit="T"))
                why = implausible_flux(flux)
                if why is not None:
                    raise s.fail("flux_t", f"readings an MLX90393 can make: {why}", flux.tolist())
                sweeps[address] = Sweep(np.array(s.matrix("position_m", k, 3, unit="m")), flux)
        arrays = {
            name: np.array(values, dtype=bool if name == "saturated" else None)
            for name, values in columns.items()
        }
        return cls(
            addresses,
            **arrays,
            samples_per_pose=doc.integer("samples_per_pose", low=1, what="a positive integer"),
            serial=sensor.string("serial", ""),
            source=doc.string("source", ""),
            sweeps=sweeps,
            rotation=np.array(rotations) if rotations else None,
            temperature_c=np.array(temperatures) if temperatures else None,
            path=str(path),
            times_s=np.array(times) if times else None,
            hold=Hold.parse(doc.table("hold"), 3 * chips) if "hold" in doc.doc else None,
        )


def _times(row: Table, last_read: float) -> list[float]:
    """A pose's [applied, first reading, last reading] (s): in that order, and applied no
    earlier than the pose before's last reading (the poses are kept in the order the robot
    made them, one after another: `creep.dwell_loads` holds each load until the next's time)."""
    t = row.numbers("times_s", 3, unit="s")
    # 1 us: a reading's time is a clock read plus the conversion's wait, the next load's the clock
    # read after that wait: equal but for round-off on a clock that only moves by waits (the simulator's).
    if not (last_read - 1e-6 <= t[0] <= t[1] <= t[2]):
        raise row.fail(
            "times_s",
            f"[applied, first reading, last reading] in that order, applied no earlier than "
            f"the pose before's last reading ({last_read} s)",
            t,
        )
    return t


def _rotation(row: Table, gravity_dir: list[float]) -> np.ndarray:
    """A pose's R_w0: orthonormal, determinant +1, and turning its gravity_dir to down."""
    R = np.array(row.matrix("rotation", 3, 3))
    # 1e-6: a robot's orientation written with 7 digits or more; anything worse is not a rotation.
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) <= 0:
        raise row.fail("rotation", "a rotation matrix (orthonormal rows, determinant +1), R_w0", R.tolist())
    g = np.asarray(gravity_dir)
    # 1e-3 (0.06 deg): both come from one robot pose; a larger gap is a pose written wrong.
    if np.linalg.norm(g) == 0 or not np.allclose(R.T @ [0.0, 0.0, -1.0], g / np.linalg.norm(g), atol=1e-3):
        # The angle between them, for the message (a zero gravity_dir: none, printed as 90 deg).
        gap = np.degrees(np.arccos(np.clip(-R[2] @ g / max(np.linalg.norm(g), 1e-300), -1.0, 1.0)))
        raise row.fail(
            "rotation",
            f"R_w0 with R^T (0, 0, -1) = gravity_dir {gravity_dir} (they disagree by "
            f"{gap:.3g} deg: angles in degrees taken as radians, or another pose's rotation?)",
            R.tolist(),
        )
    return R


def parse_address(table: Table, key: str, value: object) -> int:
    """An address written "0x0C" (JSON has no hex literals) or as an integer."""
    number = value
    if isinstance(value, str):
        try:
            number = int(value, 16) if value.lower().startswith("0x") else int(value)
        except ValueError:
            number = None
    if (
        not isinstance(number, int)
        or isinstance(number, bool)
        or not mlx.ADDRESS_MIN <= number <= mlx.ADDRESS_MAX
    ):
        raise table.fail(key, 'an address in 0x0C-0x1B (e.g. "0x0C")', value)
    return number


def parse_addresses(table: Table, key: str) -> tuple[int, ...]:
    """A non-empty list of distinct chip addresses."""
    value = table.get(key)
    if not isinstance(value, list) or not value:
        raise table.fail(key, "a non-empty list of chip addresses", value)
    addresses = tuple(parse_address(table, f"{key}[{i}]", v) for i, v in enumerate(value))
    if len(set(addresses)) != len(addresses):
        raise table.fail(key, "addresses not used twice", value)
    return addresses
