"""Calibration datasets: what a calibration run records, simulated or real.

One JSON document (format in docs/calibration.md): per pose, the applied
wrench in the sensor frame {0} (N, Nm), the flux of each chip averaged over
``samples_per_pose`` readings (T, chip frames, stacked chip by chip), the
standard error of each mean, which chips saturated, and how the pose was made
(mass, lever arm, gravity's direction). Optionally, per chip, a position-map
sweep (the paper's stage experiment): magnet positions (m, chip frame) and the
flux read at each.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..chip import mlx90393 as mlx
from ..docfile import Table, load_json

DATASET_FORMAT = "ftsensord-calibration-dataset"
DATASET_VERSION = 1
UNITS = {"flux": "T", "wrench": "N, Nm", "length": "m", "mass": "kg"}
SPLITS = ("fit", "validation")
#: The per-pose arrays of a `Dataset`, as named in the file's "poses" entries.
POSE_FIELDS = ("split", "mass_kg", "lever_m", "gravity_dir", "wrench", "flux_t", "flux_sem_t", "saturated")


@dataclass
class Sweep:
    """A position-map sweep for one chip: ``position_m`` (k, 3) and ``flux_t`` (k, 3)."""

    position_m: np.ndarray
    flux_t: np.ndarray


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

    def __len__(self) -> int:
        return len(self.wrench)

    def select(self, mask: np.ndarray) -> Dataset:
        """The poses where ``mask`` is true (sweeps kept)."""
        return replace(self, **{name: getattr(self, name)[mask] for name in POSE_FIELDS})

    def save(self, path: str | Path) -> None:
        doc = {
            "format": DATASET_FORMAT, "version": DATASET_VERSION, "units": dict(UNITS),
            "frame": "sensor frame {0}: origin at the sensor's centre, z along the shaft towards the tip",
            "sensor": {"serial": self.serial, "addresses": [f"0x{a:02X}" for a in self.addresses]},
            "samples_per_pose": self.samples_per_pose, "source": self.source,
            "poses": [{
                "split": str(self.split[k]), "mass_kg": float(self.mass_kg[k]),
                "lever_m": self.lever_m[k].tolist(), "gravity_dir": self.gravity_dir[k].tolist(),
                "wrench": self.wrench[k].tolist(), "flux_t": self.flux_t[k].tolist(),
                "flux_sem_t": self.flux_sem_t[k].tolist(), "saturated": self.saturated[k].tolist(),
            } for k in range(len(self))],
            "position_sweeps": {f"0x{a:02X}": {"position_m": s.position_m.tolist(), "flux_t": s.flux_t.tolist()}
                                for a, s in self.sweeps.items()},
        }
        Path(path).write_text(json.dumps(doc, indent=1) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> Dataset:
        """Read and validate a dataset; errors name the file, the key and what was expected."""
        doc = Table(load_json(path), path)
        doc.only({"format", "version", "units", "frame", "sensor", "samples_per_pose", "source", "poses",
                  "position_sweeps"})
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
        for row in doc.tables("poses"):
            row.only(POSE_FIELDS)
            sat = row.get("saturated")
            if not isinstance(sat, list) or len(sat) != chips or not all(isinstance(v, bool) for v in sat):
                raise row.fail("saturated", f"{chips} booleans, one per chip", sat)
            columns["saturated"].append(sat)
            columns["split"].append(row.string("split", choices=SPLITS))
            columns["mass_kg"].append(row.number("mass_kg", low=0, unit="kg"))
            columns["lever_m"].append(row.numbers("lever_m", 3, unit="m"))
            columns["gravity_dir"].append(row.numbers("gravity_dir", 3))
            columns["wrench"].append(row.numbers("wrench", 6, unit="N, Nm"))
            columns["flux_t"].append(row.numbers("flux_t", 3 * chips, unit="T"))
            columns["flux_sem_t"].append(row.numbers("flux_sem_t", 3 * chips, unit="T"))
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
                k = len(positions) if isinstance(positions, list) else 0
                sweeps[address] = Sweep(np.array(s.matrix("position_m", k, 3, unit="m")),
                                        np.array(s.matrix("flux_t", k, 3, unit="T")))
        arrays = {name: np.array(values, dtype=bool if name == "saturated" else None)
                  for name, values in columns.items()}
        return cls(addresses, **arrays, samples_per_pose=doc.integer("samples_per_pose", low=1,
                                                                     what="a positive integer"),
                   serial=sensor.string("serial", ""), source=doc.string("source", ""), sweeps=sweeps)


def parse_address(table: Table, key: str, value: object) -> int:
    """An address written "0x0C" (JSON has no hex literals) or as an integer."""
    number = value
    if isinstance(value, str):
        try:
            number = int(value, 16) if value.lower().startswith("0x") else int(value)
        except ValueError:
            number = None
    if not isinstance(number, int) or isinstance(number, bool) or not mlx.ADDRESS_MIN <= number <= mlx.ADDRESS_MAX:
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
