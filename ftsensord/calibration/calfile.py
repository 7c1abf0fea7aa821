"""The calibration file: one versioned, human-readable JSON document per sensor.

It holds K, A and the zero with their units and frame, the chip addresses (in
the order of the flux vector), the sensor's serial, the per-chip position map,
the fit report, and a SHA-256 checksum of everything else, so a file edited by
hand or cut short is refused rather than used. Format: docs/guide/calibration.md.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ftsensord.calibration.dataset import parse_addresses
from ftsensord.calibration.nlfit import NonlinearCalibration
from ftsensord.calibration.relaxation import SiliconeCalibration
from ftsensord.calibration.thermal import CalibrationTemperature
from ftsensord.chip import mlx90393 as mlx
from ftsensord.docfile import Table, load_json
from ftsensord.errors import ConfigError
from ftsensord.model.linear import LinearModel, PositionMap

#: Largest calibration file read, bytes: the packaged ones (8 chips, nonlinear model
#: included) are 22 KB; 64 KiB is three times that. A reload parses it in a worker thread,
#: but json.loads holds the GIL throughout: at this size about 2 ms, within a cycle's slack
#: (docs/design/reliability.md); a 200 MB file stalled the loop for 7.75 s.
MAX_CALIBRATION_BYTES = 64 * 1024
CAL_FORMAT = "ftsensord-calibration"
CAL_VERSION = 1
CAL_UNITS = {
    "K": "N/m, Nm/rad",
    "A": "m/T, rad/T",
    "H": "T/m, T/rad",
    "zero_flux": "T",
    "wrench": "N, Nm",
    "twist": "m, rad",
    "position_map": "M: m/T, o: m",
    "nonlinear": "gap_m, ring_radius_m: m; tilt_deg: deg; offset_t: T; K: N/m, Nm/rad; zero_twist: m, rad",
}


@dataclass
class Calibration:
    """A sensor's calibration: its linear model and what it was made from."""

    model: LinearModel
    addresses: tuple[int, ...]
    serial: str = ""
    frame: str = "sensor"
    position_map: PositionMap | None = None
    report: dict[str, Any] = field(default_factory=dict)
    nonlinear: NonlinearCalibration | None = None
    #: The largest |w| per axis over the fit poses (N, Nm): K A is a first-order fit of
    #: a 1/r^3 field there, and a linear estimate far beyond it is flagged `extrapolated`.
    wrench_range: np.ndarray | None = None
    #: The chips' die temperature over the poses, and each channel's drift when they spanned
    #: enough: the temperature stage compensates to it and flags beyond it (`processing.temperature`).
    temperature: CalibrationTemperature | None = None
    #: The silicone's relaxation, when the dataset had a step-and-hold to identify it from:
    #: the daemon undoes its creep (`processing.creep`); None: it runs as a perfect spring.
    silicone: SiliconeCalibration | None = None

    def document(self) -> dict[str, Any]:
        doc: dict[str, Any] = {
            "format": CAL_FORMAT,
            "version": CAL_VERSION,
            "units": dict(CAL_UNITS),
            "sensor": {
                "serial": self.serial,
                "frame": self.frame,
                "addresses": [f"0x{a:02X}" for a in self.addresses],
            },
            "model": "w = K A (b - zero_flux); b stacks each chip's (Bx, By, Bz) in its own frame, "
            "chips in the order of sensor.addresses; w = [fx fy fz mx my mz] in the sensor frame. "
            "With chips missing: w = K pinv(H_S) (b_S - zero_S) over the channels S left. "
            "With room_directions R (unit columns): b - zero_flux is first projected off them, "
            "(I - R R^T) (b - zero_flux), so a uniform field (the Earth's) gives no wrench",
            "K": self.model.K.tolist(),
            "A": self.model.A.tolist(),
            "zero_flux": self.model.zero.tolist(),
            "fit_report": self.report,
        }
        if self.model.H is not None:
            doc["H"] = self.model.H.tolist()
        if self.model.room is not None:
            doc["room_directions"] = self.model.room.tolist()
        if self.wrench_range is not None:
            doc["wrench_range"] = self.wrench_range.tolist()
        if self.temperature is not None:
            doc["temperature_c"] = self.temperature.document()
        if self.position_map is not None:
            doc["position_map"] = {"M": self.position_map.M.tolist(), "o": self.position_map.o.tolist()}
        if self.nonlinear is not None:
            doc["nonlinear"] = self.nonlinear.document()
        if self.silicone is not None:
            doc["silicone"] = self.silicone.document()
        doc["checksum"] = checksum(doc)
        return doc

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.document(), indent=1) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> Calibration:
        """Read and validate; errors name the file, the key and what was expected."""
        raw = load_json(path, MAX_CALIBRATION_BYTES, "calibration file")
        doc = Table(raw, path)
        doc.only(
            {
                "format",
                "version",
                "units",
                "sensor",
                "model",
                "K",
                "A",
                "H",
                "zero_flux",
                "fit_report",
                "wrench_range",
                "position_map",
                "nonlinear",
                "room_directions",
                "temperature_c",
                "silicone",
                "checksum",
            }
        )
        if doc.get("format") != CAL_FORMAT:
            raise doc.fail("format", f'"{CAL_FORMAT}"', doc.get("format"))
        doc.integer(
            "version",
            what=f"{CAL_VERSION} (this ftsensord reads version {CAL_VERSION})",
            low=CAL_VERSION,
            high=CAL_VERSION,
        )
        if doc.get("units") != CAL_UNITS:
            raise doc.fail("units", str(CAL_UNITS), doc.get("units"))
        sensor = doc.table("sensor")
        sensor.only({"serial", "frame", "addresses"})
        addresses = parse_addresses(sensor, "addresses")
        n = 3 * len(addresses)
        K = np.array(doc.matrix("K", 6, 6, unit="N/m, Nm/rad"))
        A = np.array(doc.matrix("A", 6, n, unit="m/T, rad/T"))
        zero = np.array(doc.numbers("zero_flux", n, unit="T"))
        H = np.array(doc.matrix("H", n, 6, unit="T/m, T/rad")) if "H" in raw else None
        room = None
        if "room_directions" in raw:
            room = np.array(doc.matrix("room_directions", n, 3, unit="unit vectors"))
            # 1e-9: orthonormal to the 17 digits JSON keeps; a hand edit is far off it.
            if not np.allclose(room.T @ room, np.eye(3), atol=1e-9):
                raise doc.fail("room_directions", f"{n} x 3 with orthonormal columns", "columns that are not")
        wrench_range = None
        if "wrench_range" in raw:
            wrench_range = np.array(doc.numbers("wrench_range", 6, unit="N, Nm"))
            if np.any(wrench_range <= 0):
                raise doc.fail("wrench_range", "6 numbers over 0 (N, Nm)", raw["wrench_range"])
        temperature = _temperature(doc, n) if "temperature_c" in raw else None
        pmap = None
        if "position_map" in raw:
            pm = doc.table("position_map")
            pm.only({"M", "o"})
            M = pm.get("M")
            if not isinstance(M, list) or len(M) != len(addresses):
                raise pm.fail("M", f"{len(addresses)} 3x3 matrices, one per chip", M)
            # Each chip's M named as position_map.M[i] (the item's key joined to its list's).
            Ms = [Table({f"[{i}]": m}, path, pm.key("M")).matrix(f"[{i}]", 3, 3) for i, m in enumerate(M)]
            pmap = PositionMap(np.array(Ms), np.array(pm.matrix("o", len(addresses), 3, unit="m")))
        nonlinear = _nonlinear(doc, len(addresses)) if "nonlinear" in raw else None
        silicone = SiliconeCalibration.parse(doc.table("silicone")) if "silicone" in raw else None
        report = doc.get("fit_report", {})
        if not isinstance(report, dict):
            raise doc.fail("fit_report", "a table", report)
        stored = doc.string("checksum")
        where = _not_finite(raw)
        if where is not None:  # in a part no parser above reads: the checksum's JSON has no NaN
            raise ConfigError(
                f"{path}: {where}: expected finite numbers (JSON has none other; `ftsensord "
                "calibrate` writes none), got NaN or Infinity"
            )
        if stored != checksum(raw):
            raise doc.fail("checksum", f"{checksum(raw)} (the file was changed after it was written)", stored)
        if np.linalg.matrix_rank(K @ A) < 6:
            raise doc.fail("K", "K A of rank 6 (a sensor must see all six axes)", "a rank-deficient K A")
        for key, stiffness in (("K", K), ("nonlinear.K", None if nonlinear is None else nonlinear.K)):
            if stiffness is not None:
                try:
                    lowest = float(np.linalg.eigvalsh(0.5 * stiffness + 0.5 * stiffness.T)[0])
                except np.linalg.LinAlgError:  # entries near the float range's end (1e308): none to speak of
                    lowest = float("nan")
                if not lowest > 0:  # the test `fit.check_stiffness` makes, for a file
                    raise ConfigError(
                        f"{path}: {key}: expected a positive definite stiffness (x^T K x > 0), "
                        f"got one whose symmetric part has eigenvalue {lowest:.3g}"
                    )
        return cls(
            LinearModel(K, A, zero, H, room),
            addresses,
            sensor.string("serial", ""),
            sensor.string("frame", "sensor"),
            pmap,
            report,
            nonlinear,
            wrench_range,
            temperature,
            silicone,
        )


def _temperature(doc: Table, channels: int) -> CalibrationTemperature:
    """The ``temperature_c`` section (`CalibrationTemperature.document` writes it)."""
    t = doc.table("temperature_c")
    t.only({"mean", "lowest", "highest", "drift_t_per_k"})
    low, high = mlx.OPERATING_RANGE_C  # the chips' operating range, as a dataset's
    mean, lowest, highest = (
        t.number(k, low=low, high=high, unit="degC") for k in ("mean", "lowest", "highest")
    )
    if not lowest <= mean <= highest:
        raise doc.fail("temperature_c", "lowest <= mean <= highest (degC)", doc.get("temperature_c"))
    drift = np.array(t.numbers("drift_t_per_k", channels, unit="T/K")) if "drift_t_per_k" in t.doc else None
    return CalibrationTemperature(mean, lowest, highest, drift)


def _nonlinear(doc: Table, chips: int) -> NonlinearCalibration:
    """The ``nonlinear`` section (`NonlinearCalibration.document` writes it)."""
    t = doc.table("nonlinear")
    t.only(
        {
            "gap_m",
            "ring_radius_m",
            "tilt_deg",
            "scale",
            "offset_t",
            "K",
            "zero_twist",
            "fit_rms_residual_t",
            "magnet_p_m",
            "magnet_strength",
            "warnings",
            "field_model",
        }
    )
    warnings = t.get("warnings", [])
    if not isinstance(warnings, list) or not all(isinstance(w, str) for w in warnings):
        raise t.fail("warnings", "a list of strings", warnings)
    scale_raw = t.get("scale")
    if (
        isinstance(scale_raw, list)
        and scale_raw
        and isinstance(scale_raw[0], list)
        and scale_raw[0]
        and isinstance(scale_raw[0][0], list)
    ):  # a full 3 x 3 response per chip
        if len(scale_raw) != chips:
            raise t.fail("scale", f"{chips} 3x3 matrices, one per chip, or {chips} x 3 gains", scale_raw)
        scale = np.array(
            [
                Table({"scale": m}, t.path, f"{t.key('scale')}[{i}]").matrix("scale", 3, 3)
                for i, m in enumerate(scale_raw)
            ]
        )
    else:
        scale = np.array(t.matrix("scale", chips, 3))
    magnet_p = np.array(t.matrix("magnet_p_m", chips, 3, unit="m")) if "magnet_p_m" in t.doc else None
    strength = None
    if "magnet_strength" in t.doc:
        strength = np.array(t.numbers("magnet_strength", chips))
        if np.any(strength <= 0):
            raise t.fail(
                "magnet_strength", f"{chips} numbers over 0 (relative moments)", t.get("magnet_strength")
            )
    return NonlinearCalibration(
        t.number("gap_m", low=1e-3, high=20e-3, unit="m"),
        scale,
        np.array(t.matrix("offset_t", chips, 3, unit="T")),
        np.array(t.matrix("K", 6, 6, unit="N/m, Nm/rad")),
        np.array(t.numbers("zero_twist", 6, unit="m, rad")),
        t.number("fit_rms_residual_t", low=0, unit="T"),
        t.number("ring_radius_m", low=1e-3, high=0.1, unit="m"),
        t.number("tilt_deg", low=-90, high=90),
        tuple(warnings),
        magnet_p,
        strength,
        t.string("field_model", "dipole", choices=("dipole", "dipole+octupole")) == "dipole+octupole",
    )


def _not_finite(value: Any, where: str = "") -> str | None:
    """The key path (``a.b[3]``) of the first NaN or infinity in ``value``, or None."""
    if isinstance(value, float):
        return None if math.isfinite(value) else where
    items = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else ()
    for k, v in items:
        found = _not_finite(v, f"{where}[{k}]" if isinstance(k, int) else f"{where}.{k}" if where else str(k))
        if found is not None:
            return found
    return None


def checksum(doc: dict[str, Any]) -> str:
    """SHA-256 of the canonical JSON of ``doc`` without its "checksum" key."""
    body = {k: v for k, v in doc.items() if k != "checksum"}
    text = json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return "sha256:" + hashlib.sha256(text.encode()).hexdigest()
