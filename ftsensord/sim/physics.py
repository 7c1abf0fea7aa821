"""The physical scene: sensors of chips and magnets, a stiffness, loads over time,
the room's field and the sensors' orientations in it.

For a chip of sensor s at time t: the load gives the wrench on the centre
piece; the stiffness turns it into the deflection twist xi (w = K xi, plus an
optional stiffening term); the chips move with T = exp(xi); each chip sees the
field of its own magnet and, with crosstalk on, of the sensor's other magnets,
plus the room's uniform field (fixed in the world) turned into its frame by the
sensor's orientation R_w0(t) and the deflection, plus any stray point dipoles
fixed in the world (motors) at the chip's actual position; an as-built chip then
reads it with its own gain per axis.

Model only what the scene requires: the own magnet defaults to the exact
cylinder field (the dipole errs by about 30 uT at the 6 mm gap, ten times the
reading noise) and crosstalk to dipoles (the neighbours are 10 mm or more away,
where the dipole's error is below the noise). docs/design/physics.md has the figure.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ftsensord.chip import mlx90393 as mlx
from ftsensord.model import se3
from ftsensord.model.geometry import SensorGeometry, as_built
from ftsensord.model.linear import SENSOR_RANGE
from ftsensord.model.magnet import (
    NDFEB_BR_TEMPCO_PER_K,  # noqa: F401  (its old home: the name still works here)
    cylinder_field,
    dipole_field,
    remanence_factor,
)
from ftsensord.model.silicone import stiffness_factor
from ftsensord.model.viscoelastic import Relaxation
from ftsensord.sim.heat import ChipDrift, TemperatureProfile
from ftsensord.sim.loads import DOWN, IDENTITY, NO_LOAD, FixedOrientation, G, Load, Orientation, StaticLoad
from ftsensord.sim.memory import SiliconeMemory
from ftsensord.sim.person import Person

#: Stiffness default: the diagonal of the paper's K, in N/m and Nm/rad (their
#: signs dropped: a stiffness is positive definite).
PAPER_STIFFNESS_DIAG = (8.82e3, 12.77e3, 6.50e3, 10.0, 10.0, 10.0)

_NO_FIELD = np.zeros(3)

FIELD_MODELS = ("dipole", "cylinder")
CROSSTALK_MODELS = ("off", "dipole", "cylinder")

#: The scene moves in steps of this (s): loads and temperature are sampled on
#: this grid. The silicone settles in tens of ms, so 1 ms loses nothing, and the
#: chips read within one step share one evaluation of the field.
TIME_STEP_S = 1e-3

#: Newton on the stiffening law stops when the step is below this fraction of
#: the deflection range: 1e-12 of 6 mm is far below any field change a chip sees.
NEWTON_TOL = 1e-12


@dataclass(frozen=True)
class Tolerances:
    """Standard deviations of a hand-made sensor's departures from its drawing.

    ``magnet_position_m`` per axis (m), ``magnet_remanence_rel`` (fraction),
    ``chip_tilt_rad`` per axis of a chip's rotation vector (rad), ``chip_gain_rel``
    per axis of a chip's sensitivity (fraction), ``ring_radius_m`` (m, one draw for
    the whole ring). ``seed`` names the part: the same seed builds the same sensor.
    """

    magnet_position_m: float = 0.0
    magnet_remanence_rel: float = 0.0
    chip_tilt_rad: float = 0.0
    chip_gain_rel: float = 0.0
    ring_radius_m: float = 0.0
    seed: int = 0

    def build(
        self, radius_m: float = 8e-3, tilt_deg: float = 25.0, gap_m: float = 6e-3
    ) -> tuple[SensorGeometry, np.ndarray]:
        """The as-built geometry and the chips' gains (n, 3) of `build_part`."""
        geometry, gains, _ = self.build_part(radius_m, tilt_deg, gap_m)
        return geometry, gains

    def build_part(
        self, radius_m: float = 8e-3, tilt_deg: float = 25.0, gap_m: float = 6e-3
    ) -> tuple[SensorGeometry, np.ndarray, list[ChipDrift]]:
        """The as-built geometry, the chips' gains (n, 3) and their drifts with temperature,
        drawn once from ``seed`` in a fixed order (ring radius; magnets' positions and
        remanence, chips' tilts; gains; drifts, from the datasheet's spread): every draw is
        made whatever its deviation, so setting one tolerance to 0 leaves the others' draws
        of the same seed unchanged, and the drifts, drawn last, left every earlier draw as
        it was before they existed."""
        rng = np.random.default_rng(self.seed)
        radius = radius_m + rng.normal() * self.ring_radius_m
        if radius <= 0:  # no ring: a tolerance written in the wrong unit
            raise ValueError(
                f"ring radius tolerance {self.ring_radius_m * 1e3} mm drew a radius of {radius * 1e3:.3g} mm"
            )
        nominal = SensorGeometry.ring(radius_m=radius, tilt_deg=tilt_deg, gap_m=gap_m)
        geometry = as_built(
            nominal,
            rng,
            magnet_position_m=self.magnet_position_m,
            magnet_strength_rel=self.magnet_remanence_rel,
            chip_tilt_rad=self.chip_tilt_rad,
        )
        gains = 1.0 + rng.normal(0.0, 1.0, (nominal.n_chips, 3)) * self.chip_gain_rel
        return geometry, gains, ChipDrift.draw(rng, nominal.n_chips)


@dataclass
class SimSensor:
    """One sensor in the scene: its 8 chip addresses, geometry, stiffness, load,
    orientation in the world, and each chip's gain per axis (default 1).

    ``tool_mass_kg`` at ``tool_com_m`` (m, frame {0}) hangs on the sensor: its weight
    turns with the orientation, f = m R_w0^T g, moment c x f, added to the load.

    ``stiffening`` s makes the silicone stiffer at large deflection:
    w = K (xi + s xi (xi / xi_range)^2) per axis, xi_range being the deflection
    at the sensor's range; s = 0.3 is 30 % stiffer at full range.

    ``temperature`` is the sensor's own (None: the scene's); ``chip_drift`` each chip's
    drift with it (None: every chip at the datasheet's figures, `ChipDrift.typical`).

    ``relaxation``: the silicone's Prony series (None: a perfect spring); ``stiffness`` is
    then the long-term stiffness K_inf, and the load's history drives the deflection
    (`sim.memory`, docs/design/physics.md "The silicone's memory").
    """

    name: str
    addresses: tuple[int, ...]
    geometry: SensorGeometry = field(default_factory=SensorGeometry.ring)
    stiffness: np.ndarray = field(default_factory=lambda: np.diag(PAPER_STIFFNESS_DIAG))
    stiffening: float = 0.0
    load: Load = field(default_factory=lambda: NO_LOAD)
    orientation: Orientation = field(default_factory=lambda: IDENTITY)
    chip_gain: np.ndarray | None = None
    tool_mass_kg: float = 0.0
    tool_com_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    temperature: TemperatureProfile | None = None
    chip_drift: list[ChipDrift] | None = None
    #: Where the sensor's centre is in the world (m): what a stray source's distance is from.
    centre_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    relaxation: Relaxation | None = None
    #: An MPU-6050 fixed to the sensor's holder, its axes along {0}, at this address (None: none).
    imu_address: int | None = None

    def wrench(self, t: float) -> np.ndarray:
        """The wrench on the centre piece (N, Nm, frame {0}) at ``t``: the load and the tool's weight."""
        w = self.load.wrench(t)
        if self.tool_mass_kg == 0.0:
            return w
        f = self.tool_mass_kg * G * (self.orientation.rotation(t).T @ DOWN)
        return w + np.concatenate([f, np.cross(self.tool_com_m, f)])

    def __post_init__(self) -> None:
        self.stiffness = np.asarray(self.stiffness, dtype=float)
        if len(self.addresses) != self.geometry.n_chips:
            raise ValueError(
                f"{self.name}: {len(self.addresses)} addresses for {self.geometry.n_chips} chips"
            )
        if self.chip_drift is not None and len(self.chip_drift) != self.geometry.n_chips:
            raise ValueError(
                f"{self.name}: {len(self.chip_drift)} chip drifts for {self.geometry.n_chips} chips"
            )
        if self.chip_gain is not None:
            self.chip_gain = np.asarray(self.chip_gain, dtype=float)
            if self.chip_gain.shape != (self.geometry.n_chips, 3) or np.any(self.chip_gain <= 0):
                raise ValueError(
                    f"{self.name}: chip_gain must be {self.geometry.n_chips} x 3 positive numbers"
                )
        K = self.stiffness
        if K.shape != (6, 6) or not np.allclose(K, K.T) or np.any(np.linalg.eigvalsh(K) <= 0):
            raise ValueError(f"{self.name}: stiffness must be a 6x6 symmetric positive definite matrix")
        self.xi_range = np.abs(np.linalg.solve(K, SENSOR_RANGE))
        self.memory: SiliconeMemory | None = None  # the scene gives it its time step

    @property
    def constant_load(self) -> bool:
        """The wrench never changes: a static load, and no tool's weight turning with the sensor."""
        return isinstance(self.load, StaticLoad) and (
            self.tool_mass_kg == 0.0 or isinstance(self.orientation, FixedOrientation)
        )

    def deflection(self, w: np.ndarray) -> np.ndarray:
        """The deflection twist xi (m, rad) under wrench ``w`` (N, Nm)."""
        xi = np.linalg.solve(self.stiffness, w)
        if self.stiffening == 0:
            return xi
        for _ in range(50):  # monotone law: Newton from the linear guess converges fast
            r = xi / self.xi_range
            residual = self.stiffness @ (xi + self.stiffening * xi * r * r) - w
            jac = self.stiffness @ np.diag(1 + 3 * self.stiffening * r * r)
            step = np.linalg.solve(jac, residual)
            xi = xi - step
            if np.all(np.abs(step) <= NEWTON_TOL * self.xi_range):
                return xi
        raise RuntimeError(f"{self.name}: stiffening law did not converge for w = {w}")


#: A stray source closer than this to a sensor's centre is refused (m): the ring's chips
#: are 8 mm out and the shell about as far again, so nearer it would touch the part, and
#: a motor (cm across) is no point dipole within a few of its own sizes.
STRAY_MIN_DISTANCE_M = 20e-3


@dataclass(frozen=True)
class StraySource:
    """A point dipole fixed in the world (a motor a few cm from the tool): ``position_m``
    (m) and ``moment_am2`` (A m^2), both in the world frame; its moment is scaled by
    ``scale`` at ``times_s`` (linear between, held at the ends) as the motor's current
    changes; without rows, by 1 at all times."""

    position_m: np.ndarray
    moment_am2: np.ndarray
    times_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    scale: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def moment_at(self, t: float) -> np.ndarray:
        """The moment at time ``t`` (A m^2, world frame)."""
        if len(self.times_s) == 0:
            return self.moment_am2
        return float(np.interp(t, self.times_s, self.scale)) * self.moment_am2


class PhysicalScene:
    """Sensors on one bus; implements the chips' `FieldSource` (field_t, temperature_c),
    and gives each chip its drift with temperature (`chip_drift`).

    ``temperature_c`` and ``temperature_drift_c_per_s`` are the temperature of every sensor
    without its own (`SimSensor.temperature`).
    """

    def __init__(
        self,
        sensors: list[SimSensor],
        *,
        field_model: str = "cylinder",
        crosstalk: str = "dipole",
        temperature_c: float = 25.0,
        temperature_drift_c_per_s: float = 0.0,
        time_step_s: float = TIME_STEP_S,
        external_field_t: np.ndarray | None = None,
        stray_sources: list[StraySource] | None = None,
    ):
        if field_model not in FIELD_MODELS:
            raise ValueError(f"field_model must be one of {FIELD_MODELS}, got {field_model!r}")
        if crosstalk not in CROSSTALK_MODELS:
            raise ValueError(f"crosstalk must be one of {CROSSTALK_MODELS}, got {crosstalk!r}")
        self.sensors = sensors
        self.field_model = field_model
        self.crosstalk = crosstalk
        self.temperature = TemperatureProfile.linear(temperature_c, temperature_drift_c_per_s)
        self.time_step_s = time_step_s
        self.external_field_t = np.zeros(3) if external_field_t is None else external_field_t
        self.stray_sources = list(stray_sources or [])
        for sensor in sensors:  # only a sensor whose silicone has a memory pays for one
            sensor.memory = (
                None if sensor.relaxation is None else SiliconeMemory(sensor.relaxation, time_step_s)
            )
        self._chip_of: dict[int, tuple[int, int]] = {}
        for s, sensor in enumerate(sensors):
            for i, address in enumerate(sensor.addresses):
                if address in self._chip_of:
                    raise ValueError(f"address 0x{address:02X} is used twice")
                self._chip_of[address] = (s, i)
        self._cache: dict[int, tuple[bytes, np.ndarray]] = {}
        self.faults: list = []  # ftsensord.sim.faults.Fault, applied by the simulated bus
        self.person: Person | None = None  # who follows `ftsensord guide` (None: the typical one)

    @property
    def addresses(self) -> tuple[int, ...]:
        return tuple(sorted(self._chip_of))

    @property
    def external_field_t(self) -> np.ndarray:
        """The room's uniform field in the world frame (T): the Earth's, or a motor's."""
        return self._external_field_t

    @external_field_t.setter
    def external_field_t(self, value: np.ndarray) -> None:
        field_t = np.asarray(value, dtype=float)
        if field_t.shape != (3,) or not np.all(np.isfinite(field_t)):
            raise ValueError(f"external_field_t must be 3 finite numbers (T), got {value!r}")
        self._external_field_t = field_t
        self._room_on = bool(np.any(field_t))

    def temperature_c(self, address: int, t: float) -> float:
        """The die temperature (degC) of the chip at ``address``: its sensor's at ``t`` (s)."""
        return self._profile(self.sensors[self._chip_of[address][0]]).at(t)

    def chip_drift(self, address: int) -> ChipDrift:
        """How the chip at ``address`` drifts with temperature (its part's, or typical)."""
        s, i = self._chip_of[address]
        drifts = self.sensors[s].chip_drift
        return ChipDrift.typical() if drifts is None else drifts[i]

    def _profile(self, sensor: SimSensor) -> TemperatureProfile:
        return self.temperature if sensor.temperature is None else sensor.temperature

    def set_load(self, sensor: int | str, load: Load) -> None:
        self._sensor(sensor).load = load

    def set_orientation(self, sensor: int | str, orientation: Orientation) -> None:
        """Turn a sensor in the world (its load is unchanged: it is given in {0})."""
        self._sensor(sensor).orientation = orientation

    def orientation_of(self, sensor: int | str, t: float) -> np.ndarray:
        """R_w0 of a sensor at ``t`` (s): what an IMU fixed to it sees gravity through."""
        return self._sensor(sensor).orientation.rotation(t)

    def _sensor(self, sensor: int | str) -> SimSensor:
        if isinstance(sensor, int):
            return self.sensors[sensor]
        for s in self.sensors:
            if s.name == sensor:
                return s
        raise KeyError(f"no sensor {sensor!r}; the scene has {', '.join(s.name for s in self.sensors)}")

    def field_t(self, address: int, t: float) -> np.ndarray:
        s, i = self._chip_of[address]
        sensor = self.sensors[s]
        k = math.floor(t / self.time_step_s)
        t = k * self.time_step_s
        if sensor.memory is None:
            w = np.asarray(sensor.wrench(t), dtype=float)
        else:  # the load's history, through the silicone's creep: K_inf xi = w_eff
            w = sensor.memory.effective(k, sensor.wrench, sensor.constant_load)
        scale = 1.0
        profile = self._profile(sensor)
        if not profile.is_reference:  # a scene held at 25 degC pays nothing for heat
            delta_k = profile.at(t) - mlx.TEMPERATURE_REF_C
            scale = remanence_factor(delta_k)
            w = w / stiffness_factor(delta_k)  # K(T) xi = w is K xi = w / factor, stiffening too
        # The room's field in {0}: only the turning sensor makes it change (and a field-free
        # room needs no orientation at all: the common case stays as cheap as before).
        room = sensor.orientation.rotation(t).T @ self.external_field_t if self._room_on else _NO_FIELD
        # Stray sources in {0}: only a scene with one pays for it.
        stray = self._stray_in_sensor(sensor, t) if self.stray_sources else None
        # Keyed on the load, not the deflection: the deflection (a solve) only when it changed.
        key = np.concatenate([w, [scale], room] + ([] if stray is None else [stray.ravel()])).tobytes()
        cached = self._cache.get(s)
        if cached is None or cached[0] != key:
            xi = sensor.deflection(w)
            # One vectorised evaluation serves every chip of the sensor read in this step.
            fields = self.chip_fields(
                sensor.geometry,
                se3.exp_se3(xi),
                magnet_scale=scale,
                room_t=room if self._room_on else None,
                stray=stray,
            )
            if sensor.chip_gain is not None:
                fields = fields * sensor.chip_gain  # the chip's sensitivity, before its ADC
            cached = (key, fields)
            self._cache[s] = cached
        return cached[1][i]

    def _stray_in_sensor(self, sensor: SimSensor, t: float) -> np.ndarray:
        """The stray sources seen from ``sensor`` at ``t``: (k, 2, 3), each source's
        position (m) and moment (A m^2) in frame {0}. The sensor turns about its centre
        (``sensor.centre_m`` in the world), so a source fixed in the world turns the other
        way in {0}."""
        R = sensor.orientation.rotation(t)
        return np.array(
            [[R.T @ (src.position_m - sensor.centre_m), R.T @ src.moment_at(t)] for src in self.stray_sources]
        )

    def chip_fields(
        self,
        geometry: SensorGeometry,
        T: np.ndarray,
        chips: list[int] | None = None,
        *,
        magnet_scale: float = 1.0,
        room_t: np.ndarray | None = None,
        stray: np.ndarray | None = None,
    ) -> np.ndarray:
        """Field (T) at chips (default: all), each in its own frame, centre piece at pose T.

        ``magnet_scale`` scales the magnets' field (their remanence against temperature);
        ``room_t`` is a uniform field in frame {0} (T) added to it: a chip turned by the
        deflection sees it turned too. ``stray`` (k, 2, 3): point dipoles' positions (m)
        and moments (A m^2) in {0} (`_stray_in_sensor`), each evaluated at every chip's
        deflected position.
        """
        idx = np.arange(geometry.n_chips) if chips is None else np.asarray(chips)
        R_chips = np.einsum("ij,njk->nik", T[:3, :3], geometry.chip_R[idx])
        p_chips = geometry.chip_p[idx] @ T[:3, :3].T + T[:3, 3]
        fields = own_magnet_field(geometry, p_chips, idx, self.field_model)
        if self.crosstalk != "off":
            other = magnet_fields(geometry, p_chips, self.crosstalk)
            other[np.arange(len(idx)), idx] = 0.0  # the own magnet is counted above
            fields = fields + other.sum(axis=1)
        fields = magnet_scale * fields
        if room_t is not None:
            fields = fields + room_t
        if stray is not None:
            for position, moment in stray:
                fields = fields + dipole_field(p_chips - position, moment)
        return np.einsum("nji,nj->ni", R_chips, fields)


def _field(geometry: SensorGeometry, r: np.ndarray, magnets: np.ndarray, model: str) -> np.ndarray:
    """Field (T, frame {0}) at offsets ``r`` (..., 3) from the magnets ``magnets`` (...)."""
    axes = geometry.magnet_axis[magnets]
    strength = geometry.strengths[magnets][..., None]  # both fields are linear in Br
    if model == "dipole":
        return dipole_field(r, geometry.magnet_moment_am2 * strength * axes)
    R = geometry.magnet_R[magnets]  # the cylinder field is written in the magnet's frame
    local = np.einsum("...ji,...j->...i", R, r)
    b_local = cylinder_field(local, geometry.magnet_radius_m, geometry.magnet_length_m, geometry.magnet_br_t)
    return strength * np.einsum("...ij,...j->...i", R, b_local)


def own_magnet_field(
    geometry: SensorGeometry, points: np.ndarray, chips: np.ndarray, model: str
) -> np.ndarray:
    """Field (T, frame {0}) of magnet ``chips[k]`` at ``points[k]``."""
    return _field(geometry, points - geometry.magnet_p[chips], chips, model)


def magnet_fields(geometry: SensorGeometry, points: np.ndarray, model: str) -> np.ndarray:
    """Field (T, frame {0}) of every magnet at every point: (n_points, n_magnets, 3)."""
    r = points[:, None, :] - geometry.magnet_p[None, :, :]
    magnets = np.broadcast_to(np.arange(geometry.n_chips), r.shape[:2])
    return _field(geometry, r, magnets, model)


def two_sensor_scene(**options: object) -> PhysicalScene:
    """The nominal drawing in a field-free room: two sensors of 8 chips, 0x0C-0x13 and
    0x14-0x1B, no load (the default scene, `ftsensord.sim.default_scene`, is as built, in
    the Earth's field)."""
    return PhysicalScene(
        [SimSensor("sensor1", tuple(range(0x0C, 0x14))), SimSensor("sensor2", tuple(range(0x14, 0x1C)))],
        **options,  # type: ignore[arg-type]
    )
