"""Scenes: what the emulated chips measure, and scene files.

A scene gives, per chip address, the flux density in the chip's frame (T) and
the die temperature (degC) at any time (`ftsensord.sim.chip.FieldSource`).
Two kinds exist: `StaticScene` (a given field per chip) and the physical
`ftsensord.sim.physics.PhysicalScene` (magnets, stiffness, loads over time).
Scene files (TOML) are described in docs/design/scenes.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from importlib import resources
from itertools import pairwise
from pathlib import Path

import numpy as np

from ftsensord.chip import mlx90393 as mlx
from ftsensord.chip import mpu6050
from ftsensord.docfile import Table, load_toml
from ftsensord.errors import ConfigError
from ftsensord.model.geometry import SensorGeometry
from ftsensord.sim.faults import FAULT_KINDS, NEEDS_ADDRESS, Fault
from ftsensord.sim.heat import TemperatureProfile
from ftsensord.sim.loads import (
    IDENTITY,
    NO_LOAD,
    PLANS,
    CalibrationRobotLoad,
    FixedOrientation,
    Load,
    Orientation,
    RecordedLoad,
    RecordedOrientation,
    StaticLoad,
    StepLoad,
    paper_plan,
    ramp,
)
from ftsensord.sim.memory import parse_silicone
from ftsensord.sim.person import parse_person
from ftsensord.sim.physics import (
    CROSSTALK_MODELS,
    FIELD_MODELS,
    PAPER_STIFFNESS_DIAG,
    STRAY_MIN_DISTANCE_M,
    PhysicalScene,
    SimSensor,
    StraySource,
    Tolerances,
)

SCENE_VERSION = 1


@dataclass
class StaticScene:
    """A fixed field (T, chip frame) and temperature (degC) per chip address.

    Tests change a chip's field with `set_field`; the change is seen by every
    conversion that finishes after it.
    """

    fields_t: dict[int, np.ndarray]
    temperatures_c: dict[int, float] = field(default_factory=dict)
    default_temperature_c: float = 25.0
    faults: list[Fault] = field(default_factory=list)

    @property
    def addresses(self) -> tuple[int, ...]:
        return tuple(sorted(self.fields_t))

    def field_t(self, address: int, t: float) -> np.ndarray:
        return self.fields_t[address]

    def temperature_c(self, address: int, t: float) -> float:
        return self.temperatures_c.get(address, self.default_temperature_c)

    def set_field(self, address: int, field_t: np.ndarray | list[float]) -> None:
        self.fields_t[address] = np.asarray(field_t, dtype=float)


#: The default scene's file, in the package's data: two as-built sensors (0x0C-0x13 and
#: 0x14-0x1B) in the Earth's field, at rest (docs/design/scenes.md).
DEFAULT_SCENE = "scene-default.toml"


def default_scene() -> PhysicalScene:
    """The default scene: a real room with a real part, no load (`DEFAULT_SCENE`).
    `two_sensor_scene` is the nominal drawing in a field-free room."""
    scene = load_scene(default_scene_path())
    assert isinstance(scene, PhysicalScene)  # the packaged file is of kind "sensors"
    return scene


def default_scene_path() -> Path:
    """Where the default scene's file is (in the installed package)."""
    return Path(str(resources.files("ftsensord") / "data" / DEFAULT_SCENE))


def default_scene_text(load: list[float] | None = None) -> str:
    """The default scene's file, with sensor1 under a static ``load`` (N, Nm) when given:
    for a scene written beside a configuration that uses the packaged calibrations (they
    were fitted on this room and part; faults may be appended as [[fault]] tables)."""
    text = default_scene_path().read_text()
    if load is None:
        return text
    table = f'[sensor.load]\nkind = "static"\nwrench = {list(load)}\n'
    return text.replace("[sensor.orientation]", table + "[sensor.orientation]", 1)  # sensor1's comes first


def _address(t: Table, name: str, value: object) -> int:
    if (
        not isinstance(value, int)
        or isinstance(value, bool)
        or not mlx.ADDRESS_MIN <= value <= mlx.ADDRESS_MAX
    ):
        raise t.fail(name, "an address in 0x0C-0x1B", value)
    return value


def _load(t: Table) -> Load:
    kind = t.string("kind", choices=("none", "static", "step", "ramp", "recorded", "robot"))
    if kind == "none":
        t.only({"kind"})
        return NO_LOAD
    if kind == "static":
        t.only({"kind", "wrench"})
        return StaticLoad(np.array(t.numbers("wrench", 6, unit="N, Nm")))
    if kind == "step":
        t.only({"kind", "at_s", "before", "after"})
        return StepLoad(
            t.number("at_s", unit="s"),
            np.array(t.numbers("before", 6, unit="N, Nm")),
            np.array(t.numbers("after", 6, unit="N, Nm")),
        )
    if kind == "ramp":
        t.only({"kind", "from_s", "to_s", "start", "end"})
        from_s, to_s = t.number("from_s", unit="s"), t.number("to_s", unit="s")
        if to_s <= from_s:
            raise t.fail("to_s", f"a time after from_s ({from_s})", to_s)
        return ramp(from_s, to_s, np.array(t.numbers("start", 6)), np.array(t.numbers("end", 6)))
    if kind == "robot":
        t.only({"kind", "plan", "poses", "dwell_s"})
        plan = paper_plan(
            t.string("plan", "six-axis", choices=sorted(PLANS)),
            n_fit=t.integer("poses", 193, low=1, what="a positive integer"),
            n_validation=0,
        )
        return CalibrationRobotLoad([pose for pose, _ in plan], t.number("dwell_s", 1.0, low=1e-3, unit="s"))
    t.only({"kind", "times_s", "wrenches"})
    times = t.numbers("times_s", unit="s")
    rows = t.get("wrenches")
    if not isinstance(rows, list) or len(rows) != len(times):
        raise t.fail("wrenches", f"{len(times)} rows, one per time", rows)
    wrenches = [
        Table({"row": r}, t.path, f"{t.key('wrenches')}[{i}]").numbers("row", 6) for i, r in enumerate(rows)
    ]
    try:
        return RecordedLoad(np.array(times), np.array(wrenches))
    except ValueError as exc:
        raise t.fail("times_s", "strictly increasing times", times) from exc


def _orientation(t: Table) -> Orientation:
    kind = t.string("kind", choices=("fixed", "recorded"))
    if kind == "fixed":
        t.only({"kind", "rotvec_deg"})
        return FixedOrientation.from_rotvec_deg(t.numbers("rotvec_deg", 3, unit="deg, rotation vector"))
    t.only({"kind", "times_s", "rotvec_deg"})
    times = t.numbers("times_s", unit="s")
    rows = t.get("rotvec_deg")
    if not isinstance(rows, list) or not times or len(rows) != len(times):
        raise t.fail("rotvec_deg", f"{len(times)} rows of 3 numbers (deg), one per time", rows)
    vectors = [
        Table({f"rotvec_deg[{i}]": r}, t.path, t.prefix).numbers(f"rotvec_deg[{i}]", 3, unit="deg")
        for i, r in enumerate(rows)
    ]
    if any(b <= a for a, b in pairwise(times)):
        raise t.fail("times_s", "strictly increasing times (s)", times)
    return RecordedOrientation.from_rotvecs_deg(times, vectors)


#: Scene keys of `[sensor.tolerances]` (standard deviations, in the units named), the
#: factor to SI (mm -> m, % -> fraction, deg -> rad), and the largest accepted. A
#: hand-made part is off by tenths of a mm, a few % and degrees; 1 mm, 15 deg or 20 %
#: and more is a unit mistake or another drawing. 20 % also keeps a magnet's or chip's
#: strength positive (a draw 5 sd below the mean: once in 3 million).
TOLERANCE_KEYS = {
    "magnet_position_mm": (1e-3, 1.0),
    "magnet_remanence_pct": (1e-2, 20.0),
    "chip_tilt_deg": (np.pi / 180, 15.0),
    "chip_gain_pct": (1e-2, 20.0),
    "ring_radius_mm": (1e-3, 1.0),
}


def _tolerances(t: Table) -> Tolerances:
    t.only({*TOLERANCE_KEYS, "seed"})
    sd = {
        k: t.number(k, 0.0, low=0.0, high=high, unit=k.rsplit("_", 1)[1] + ", standard deviation") * factor
        for k, (factor, high) in TOLERANCE_KEYS.items()
    }
    return Tolerances(
        sd["magnet_position_mm"],
        sd["magnet_remanence_pct"],
        sd["chip_tilt_deg"],
        sd["chip_gain_pct"],
        sd["ring_radius_mm"],
        t.integer("seed", low=0, what="an integer >= 0 naming the part"),
    )


#: Every temperature a scene holds is in the chips' operating range (`mlx.OPERATING_RANGE_C`):
#: the datasheet's drifts say nothing beyond, a kelvin figure (298) or a typo falls outside,
#: and a dataset recorded on the scene must load (it is held to the same range).
TEMPERATURE_RANGE_C = mlx.OPERATING_RANGE_C
TEMPERATURE_UNIT = "degC, the MLX90393's operating range"


def _temperature(t: Table) -> TemperatureProfile:
    kind = t.string("kind", choices=("constant", "linear", "recorded"))
    low, high = TEMPERATURE_RANGE_C
    unit = TEMPERATURE_UNIT
    if kind == "constant":
        t.only({"kind", "celsius"})
        return TemperatureProfile.constant(t.number("celsius", low=low, high=high, unit=unit))
    if kind == "linear":
        t.only({"kind", "celsius", "drift_c_per_s"})
        return TemperatureProfile.linear(
            t.number("celsius", low=low, high=high, unit=unit), t.number("drift_c_per_s", unit="degC/s")
        )
    t.only({"kind", "times_s", "celsius"})
    times = t.numbers("times_s", unit="s")
    if not times or any(b <= a for a, b in pairwise(times)):
        raise t.fail("times_s", "strictly increasing times (s), at least one", times)
    celsius = t.numbers("celsius", len(times), unit=f"degC, one per time in times_s, {unit}")
    if not all(low <= c <= high for c in celsius):
        raise t.fail("celsius", f"temperatures in [{low}, {high}] ({unit})", celsius)
    return TemperatureProfile(tuple(times), tuple(celsius))


def _sensor(t: Table, index: int) -> SimSensor:
    t.only(
        {
            "name",
            "addresses",
            "stiffness_diag",
            "stiffening",
            "ring_radius_mm",
            "tilt_deg",
            "gap_mm",
            "load",
            "orientation",
            "tolerances",
            "tool",
            "temperature",
            "centre_m",
            "silicone",
            "imu",
        }
    )
    addresses = t.get("addresses")
    if not isinstance(addresses, list) or len(addresses) != 8:
        raise t.fail("addresses", "8 chip addresses", addresses)
    addrs = tuple(_address(t, f"addresses[{i}]", a) for i, a in enumerate(addresses))
    stiffness = t.numbers("stiffness_diag", 6, list(PAPER_STIFFNESS_DIAG), unit="N/m x3, Nm/rad x3")
    if min(stiffness) <= 0:
        raise t.fail("stiffness_diag", "6 positive numbers (N/m x3, Nm/rad x3)", stiffness)
    shape: dict[str, float] = {
        "radius_m": t.number("ring_radius_mm", 8.0, low=1e-3, unit="mm") * 1e-3,
        "tilt_deg": t.number("tilt_deg", 25.0, low=-90, high=90, unit="deg"),
        "gap_m": t.number("gap_mm", 6.0, low=1e-3, unit="mm") * 1e-3,
    }
    gains, drifts = None, None
    if "tolerances" in t.doc:
        tol = t.table("tolerances")
        try:
            geometry, gains, drifts = _tolerances(tol).build_part(**shape)
        except ValueError as exc:
            raise t.fail("tolerances", f"tolerances that build a sensor ({exc})", tol.doc) from exc
    else:
        geometry = SensorGeometry.ring(
            radius_m=shape["radius_m"], tilt_deg=shape["tilt_deg"], gap_m=shape["gap_m"]
        )
    load = _load(t.table("load")) if "load" in t.doc else NO_LOAD
    orientation: Orientation = IDENTITY
    if "orientation" in t.doc:
        if isinstance(load, CalibrationRobotLoad):
            raise t.fail(
                "orientation",
                'no orientation with a load of kind "robot" (the robot turns the sensor through its poses)',
                t.get("orientation"),
            )
        orientation = _orientation(t.table("orientation"))
    elif isinstance(load, CalibrationRobotLoad):
        orientation = load  # the robot's poses turn the sensor
    mass_kg, com_m = 0.0, np.zeros(3)
    if "tool" in t.doc:
        if isinstance(load, CalibrationRobotLoad):
            raise t.fail(
                "tool",
                'no tool with a load of kind "robot" (the robot\'s poses carry its masses)',
                t.get("tool"),
            )
        tool = t.table("tool")
        tool.only({"mass_g", "com_mm"})
        mass_kg = tool.number("mass_g", low=0.0, high=5000.0, unit="g") * 1e-3  # 5 kg: 100 times the range
        com_m = np.array(tool.numbers("com_mm", 3, unit="mm, frame {0}")) * 1e-3
    temperature = _temperature(t.table("temperature")) if "temperature" in t.doc else None
    return SimSensor(
        t.string("name", f"sensor{index + 1}"),
        addrs,
        geometry,
        np.diag(stiffness),
        t.number("stiffening", 0.0, low=0.0),
        load,
        orientation,
        gains,
        mass_kg,
        com_m,
        temperature,
        drifts,
        np.array(t.numbers("centre_m", 3, [0.0, 0.0, 0.0], unit="m, world frame")),
        parse_silicone(t.table("silicone")) if "silicone" in t.doc else None,
        _imu(t),
    )


def _imu(t: Table) -> int | None:
    """``imu``: the address of an MPU-6050 fixed to the sensor's holder (its axes along {0})."""
    if "imu" not in t.doc:
        return None
    value = t.get("imu")
    if not isinstance(value, int) or isinstance(value, bool) or value not in mpu6050.ADDRESSES:
        raise t.fail("imu", "an MPU-6050's address, 0x68 or 0x69", value)
    return value


def _faults(doc: Table, addresses: tuple[int, ...]) -> list[Fault]:
    if "fault" not in doc.doc:
        return []
    faults = []
    for t in doc.tables("fault"):
        t.only({"kind", "at_s", "until_s", "address", "register", "value", "factor", "field_mt"})
        kind = t.string("kind", choices=FAULT_KINDS)
        address = None
        if kind in NEEDS_ADDRESS or "address" in t.doc:
            address = _address(t, "address", t.get("address"))
            if address not in addresses:
                raise t.fail("address", "an address of the scene's chips", f"0x{address:02X}")
        at = t.number("at_s", low=0, unit="s")
        until = t.number("until_s", low=at, unit="s, after at_s") if "until_s" in t.doc else float("inf")
        if until == at and kind != "drift_register":
            raise t.fail("until_s", "a time after at_s", until)
        faults.append(
            Fault(
                kind,
                at,
                until,
                address,
                register=t.integer("register", 0, low=0, high=mlx.REG_MAX),
                value=t.integer("value", 0, low=0, high=0xFFFF),
                factor=t.number("factor", 1.0, low=1.0, unit="times slower"),
                field_mt=t.number("field_mt", 60.0, unit="mT"),
            )
        )
    return faults


def _static(doc: Table) -> StaticScene:
    doc.only({"version", "kind", "temperature_c", "chip", "fault"})
    fields: dict[int, np.ndarray] = {}
    temps: dict[int, float] = {}
    for chip in doc.tables("chip"):
        chip.only({"address", "field_ut", "temperature_c"})
        addr = _address(chip, "address", chip.get("address"))
        if addr in fields:
            raise chip.fail("address", "an address not used before", addr)
        fields[addr] = np.array(chip.numbers("field_ut", 3, unit="uT, chip frame")) * 1e-6
        if "temperature_c" in chip.doc:
            temps[addr] = chip.number(
                "temperature_c",
                low=TEMPERATURE_RANGE_C[0],
                high=TEMPERATURE_RANGE_C[1],
                unit=TEMPERATURE_UNIT,
            )
    scene = StaticScene(
        fields,
        temps,
        doc.number(
            "temperature_c",
            25.0,
            low=TEMPERATURE_RANGE_C[0],
            high=TEMPERATURE_RANGE_C[1],
            unit=TEMPERATURE_UNIT,
        ),
    )
    scene.faults = _faults(doc, scene.addresses)
    return scene


def _physical(doc: Table) -> PhysicalScene:
    doc.only(
        {
            "version",
            "kind",
            "field_model",
            "crosstalk",
            "temperature_c",
            "temperature_drift_c_per_s",
            "external_field_ut",
            "sensor",
            "fault",
            "stray_source",
            "person",
        }
    )
    sensors = [_sensor(t, i) for i, t in enumerate(doc.tables("sensor"))]
    seen: set[int] = set()
    for i, s in enumerate(sensors):
        for a in s.addresses:
            if a in seen:
                raise ConfigError(
                    f"{doc.path}: sensor[{i}].addresses: expected addresses not used before, "
                    f"got 0x{a:02X} twice"
                )
            seen.add(a)
    imus = [s.imu_address for s in sensors if s.imu_address is not None]
    for i, s in enumerate(sensors):
        if s.imu_address is not None and imus.count(s.imu_address) > 1:
            raise ConfigError(
                f"{doc.path}: sensor[{i}].imu: expected an address no other sensor's IMU uses "
                f"(0x68 or 0x69: AD0 low or high), got 0x{s.imu_address:02X} twice"
            )
    scene = PhysicalScene(
        sensors,
        field_model=doc.string("field_model", "cylinder", choices=FIELD_MODELS),
        crosstalk=doc.string("crosstalk", "dipole", choices=CROSSTALK_MODELS),
        temperature_c=doc.number(
            "temperature_c",
            25.0,
            low=TEMPERATURE_RANGE_C[0],
            high=TEMPERATURE_RANGE_C[1],
            unit=TEMPERATURE_UNIT,
        ),
        temperature_drift_c_per_s=doc.number("temperature_drift_c_per_s", 0.0, unit="degC/s"),
        external_field_t=_external_field(doc),
        stray_sources=_stray_sources(doc, sensors),
    )
    scene.faults = _faults(doc, scene.addresses)
    # Who follows a guided calibration's prompts (`ftsensord guide`); None: the typical person.
    scene.person = parse_person(doc.table("person")) if "person" in doc.doc else None
    return scene


#: The strongest room field a scene may hold (uT): 5 mT is 100 times the Earth's and
#: a tenth of where a chip saturates; more is a unit mistake (mT or T written as uT
#: gives a field far smaller, nT far larger) or a magnet on the bench, not a room.
EXTERNAL_FIELD_MAX_UT = 5000.0


def _external_field(doc: Table) -> np.ndarray:
    field_ut = np.array(doc.numbers("external_field_ut", 3, [0.0, 0.0, 0.0], unit="uT, world frame, z up"))
    if np.linalg.norm(field_ut) > EXTERNAL_FIELD_MAX_UT:
        raise doc.fail(
            "external_field_ut",
            f"a room's field, |B| <= {EXTERNAL_FIELD_MAX_UT:g} uT (the Earth's is 25-65 uT)",
            field_ut.tolist(),
        )
    return field_ut * 1e-6


def _stray_sources(doc: Table, sensors: list[SimSensor]) -> list[StraySource]:
    """The `[[stray_source]]` tables: point dipoles fixed in the world (docs/design/scenes.md)."""
    if "stray_source" not in doc.doc:
        return []
    sources = []
    for t in doc.tables("stray_source"):
        t.only({"position_m", "moment_am2", "times_s", "scale"})
        position = np.array(t.numbers("position_m", 3, unit="m, world frame"))
        for s in sensors:
            distance = float(np.linalg.norm(position - s.centre_m))
            if distance < STRAY_MIN_DISTANCE_M:
                raise t.fail(
                    "position_m",
                    f"a point at least {STRAY_MIN_DISTANCE_M * 1e3:g} mm from each sensor's "
                    f"centre (a point dipole is no model of a source that near; {s.name} is "
                    f"{distance * 1e3:.3g} mm away)",
                    position.tolist(),
                )
        moment = np.array(t.numbers("moment_am2", 3, unit="A m^2, world frame"))
        if ("times_s" in t.doc) != ("scale" in t.doc):
            raise t.fail(
                "scale" if "times_s" in t.doc else "times_s", "times_s and scale given together", "missing"
            )
        times = np.array(t.numbers("times_s", default=[], unit="s"))
        scale = np.array(t.numbers("scale", default=[], unit="times moment_am2"))
        if len(scale) != len(times):
            raise t.fail("scale", f"{len(times)} numbers, one per time in times_s", scale.tolist())
        if "times_s" in t.doc and (len(times) == 0 or np.any(np.diff(times) <= 0)):
            raise t.fail("times_s", "at least one time, strictly increasing (s)", times.tolist())
        sources.append(StraySource(position, moment, times, scale))
    return sources


def load_scene(path: str | Path) -> StaticScene | PhysicalScene:
    """Read a scene file; errors name the file, the key and what was expected."""
    doc = Table(load_toml(path), path)
    version = doc.get("version", None)
    if version != SCENE_VERSION:
        raise doc.fail("version", str(SCENE_VERSION), version)
    kind = doc.string("kind", choices=("static", "sensors"))
    return _static(doc) if kind == "static" else _physical(doc)
