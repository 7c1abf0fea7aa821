"""What the calibration knows of temperature: the physical laws, and each channel's drift
when its data span temperatures.

Three laws act on a warm sensor, each a relative change per kelvin from 25 degC
(docs/design/physics.md gives their sources): the magnets' remanence
(`model.magnet.NDFEB_BR_TEMPCO_PER_K`) and each chip's sensitivity
(`chip.mlx90393.SENSITIVITY_TEMPCO_PER_K`; the residual `SENSITIVITY_TEMPCO_TCMP_PER_K`
with the chip's own compensation on) scale the flux a chip reads; the silicone's stiffness
(`model.silicone.STIFFNESS_TEMPCO_PER_K`) scales the wrench a deflection means.

What no law knows is each chip's own: its offset drift (the datasheet bounds it at
1000 LSB over the range, 2.5 uT/K on X and Y: worst-case chips, at 10 K, put 0.1-0.2 N on
a sensor at rest) and its sensitivity's departure from the typical coefficient. Both are
linear in the temperature and, at the sensor's working flux, one drift per channel (T/K):
`fit_drift` measures it from a dataset whose poses span temperatures, as the residual of
the calibration's flux model against the pose's temperature.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ftsensord.calibration.dataset import Dataset
from ftsensord.chip import mlx90393 as mlx
from ftsensord.errors import CalibrationError
from ftsensord.model.geometry import SensorGeometry
from ftsensord.model.linear import SENSOR_RANGE, LinearModel
from ftsensord.model.magnet import NDFEB_BR_TEMPCO_PER_K, remanence_factor
from ftsensord.model.silicone import STIFFNESS_TEMPCO_PER_K, stiffness_factor

#: The poses must span this many kelvin for a drift to be measured: the drift's standard
#: error is the model's residual (a few uT a pose) over sqrt(poses) x the temperatures'
#: spread; below 3 K that is 0.3 uT/K and more at 200 poses, as large as the drift of a
#: good chip. A narrower span is the calibration's temperature, with no drift.
MIN_DRIFT_SPAN_K = 3.0
#: Passes of fit -> drift -> fit on the drift-corrected flux: the fit absorbs part of the
#: drift where the plan's loads and temperatures go together, and each pass takes part of
#: the rest, until a pass changes the drift by under `DRIFT_SETTLED` of it (the warm
#: benchmark's parts 31-33 took 4-5 passes, its quick and full datasets alike; two, the former
#: fixed count, left warm parts 1.7-1.9x the 2 mNm their rest must read within); at most this
#: many, twice what they took.
DRIFT_PASSES = 10
#: A pass's change of the drift (RMS over the channels) under this share of the drift: settled.
#: 2 %: 0.05 uT/K of a 2.5 uT/K drift, 0.5 uT over a 10 K warming, a tenth of the chips' noise.
DRIFT_SETTLED = 0.02


@dataclass(frozen=True)
class ThermalLaws:
    """The three laws (relative change per K from `mlx.TEMPERATURE_REF_C`): the magnets' and
    the silicone's are the model's (`remanence_factor`, `stiffness_factor`); the chips'
    sensitivity coefficient depends on their TCMP_EN."""

    sensitivity_per_k: tuple[float, float, float] = tuple(mlx.SENSITIVITY_TEMPCO_PER_K)  # type: ignore[assignment]

    @classmethod
    def physical(cls, settings: mlx.Settings | None = None) -> ThermalLaws:
        """The physical defaults for chips at ``settings`` (TCMP_EN picks the chips' law)."""
        if settings is not None and settings.tcmp_en:
            return cls(sensitivity_per_k=(mlx.SENSITIVITY_TEMPCO_TCMP_PER_K,) * 3)
        return cls()

    def flux_gain(self, celsius: np.ndarray) -> np.ndarray:
        """g(T) = (1 + a dT)(1 + s dT) per chip and axis, (n, 3), at die temperatures ``celsius`` (n,)."""
        dt = (np.asarray(celsius, dtype=float) - mlx.TEMPERATURE_REF_C)[:, None]
        return remanence_factor(dt) * (1.0 + np.asarray(self.sensitivity_per_k) * dt)

    def stiffness_gain(self, celsius: float) -> float:
        """k(T): the silicone's stiffness against its stiffness at 25 degC."""
        return stiffness_factor(celsius - mlx.TEMPERATURE_REF_C)

    def document(self) -> dict[str, Any]:
        return {
            "magnet_per_k": NDFEB_BR_TEMPCO_PER_K,
            "sensitivity_per_k": list(self.sensitivity_per_k),
            "stiffness_per_k": STIFFNESS_TEMPCO_PER_K,
        }


@dataclass(frozen=True)
class CalibrationTemperature:
    """The chips' die temperature over a calibration's poses (degC) and, when they spanned
    `MIN_DRIFT_SPAN_K` or more, each channel's drift there (T/K, 3 per chip, chip frames),
    the laws taken out first."""

    mean_c: float
    lowest_c: float
    highest_c: float
    drift_t_per_k: np.ndarray | None = None

    def document(self) -> dict[str, Any]:
        doc: dict[str, Any] = {"mean": self.mean_c, "lowest": self.lowest_c, "highest": self.highest_c}
        if self.drift_t_per_k is not None:
            doc["drift_t_per_k"] = self.drift_t_per_k.tolist()
        return doc


def to_reference(
    flux: np.ndarray,
    celsius: np.ndarray,
    reference_c: float,
    laws: ThermalLaws,
    drift_t_per_k: np.ndarray | None = None,
) -> np.ndarray:
    """Flux (poses, 3 chips) read at ``celsius`` (poses,) as it would read at ``reference_c``:
    the laws undone, then each channel's drift."""
    chips = flux.shape[1] // 3
    scale = laws.flux_gain(np.array([reference_c]))[0] / laws.flux_gain(celsius)  # (poses, 3)
    out = flux * np.tile(scale, chips)
    if drift_t_per_k is not None:
        out = out - np.outer(celsius - reference_c, drift_t_per_k)
    return out


def _curvature(wrench: np.ndarray) -> np.ndarray:
    """Each pose's load's second-order terms (n x 21: w_i w_j, i <= j, of the range-scaled load):
    what a linear model's residual holds of the part's own curvature."""
    w = wrench / SENSOR_RANGE
    i, j = np.triu_indices(6)
    return w[:, i] * w[:, j]


def fit_drift(
    dataset: Dataset, model: LinearModel, reference_c: float, geometry: SensorGeometry | None = None
) -> np.ndarray:
    """Each channel's drift (T/K) from the fit and no-load poses of ``dataset`` (flux already
    at ``reference_c`` by the laws): the flux model's residual b - b0 - H K^-1 w, regressed
    on the pose's temperature beside a constant per channel (the zero's business), the load's
    second-order terms per channel (`_curvature`: the linear model's own error, which would
    leak into the drift wherever the plan's loads and temperatures go together, as a robot
    cell warming through a plan ordered by orientation does), and the room's field. With each
    pose's orientation recorded, the room's field is one vector in the world, R_w0^T B in {0},
    seen by the chips through the geometry's orientations (3 unknowns in all), and the whole
    drift is measured; without them, the room's field is free at every pose and the drift
    along its 3 directions is left at 0 (the model is blind to them anyway: a drift there
    changes no wrench)."""
    if model.H is None or dataset.temperature_c is None:
        raise CalibrationError("a drift needs the flux model H and the poses' temperatures")
    poses = dataset.select(np.isin(dataset.split, ("fit", "no-load")) & ~dataset.saturated.any(axis=1))
    predicted = model.zero + np.linalg.solve(model.K, poses.wrench.T).T @ model.H.T
    residual = poses.flux_t - predicted
    assert poses.temperature_c is not None  # (the selection keeps the dataset's temperatures)
    dt: np.ndarray = poses.temperature_c - reference_c
    # Per pose, shared by every channel: temperature, a constant, the load's curvature.
    own = np.column_stack([dt, np.ones(len(dt)), _curvature(poses.wrench)])
    n, m = residual.shape
    if poses.rotation is None:
        room = (geometry or SensorGeometry.ring()).room_directions()
        residual = residual - (residual @ room) @ room.T
        solution, *_ = np.linalg.lstsq(own, residual, rcond=None)
        return solution[0]
    seen = np.concatenate([R.T for R in (geometry or SensorGeometry.ring()).chip_R], axis=0)  # (m, 3)
    # Unknowns: each of ``own``'s columns per channel (k x m, column-major by term), B (3, world).
    # Rows: pose p, channel c.
    k = own.shape[1]
    design = np.zeros((n * m, k * m + 3))
    eye = np.eye(m)
    for p in range(n):
        rows = slice(p * m, (p + 1) * m)
        design[rows, : k * m] = np.kron(own[p], eye)
        design[rows, k * m :] = seen @ poses.rotation[p].T
    solution, *_ = np.linalg.lstsq(design, residual.ravel(), rcond=None)
    return solution[:m]


def calibration_temperature(dataset: Dataset) -> CalibrationTemperature | None:
    """The dataset's temperatures, without a drift (None: not recorded)."""
    span = dataset.temperature_range()
    return None if span is None else CalibrationTemperature(*span)


def thermal_fit(
    dataset: Dataset, fit_model: Any, laws: ThermalLaws = ThermalLaws()
) -> tuple[Dataset, CalibrationTemperature | None, Any]:
    """The dataset brought to its mean temperature, its temperatures with each channel's
    drift where they span `MIN_DRIFT_SPAN_K`, and ``fit_model(dataset)``'s result on it
    (its ``.model`` the linear model): the laws first, then `DRIFT_PASSES` of fit and drift.
    ``fit_model`` takes ``room_field`` (`fit.ROOM_FIELD_MODES`): the first pass of a drift uses
    the nominal room directions, as the no-load poses that measure them vary with the drift
    too (at 2.5 uT/K, more than the room's field turned does)."""
    temperature = calibration_temperature(dataset)
    if temperature is None:
        return dataset, None, fit_model(dataset)
    celsius = dataset.temperature_c
    assert celsius is not None  # recorded: the temperature is known
    lawful = replace(dataset, flux_t=to_reference(dataset.flux_t, celsius, temperature.mean_c, laws))
    if temperature.highest_c - temperature.lowest_c < MIN_DRIFT_SPAN_K:
        return lawful, temperature, fit_model(lawful)
    drift = np.zeros(dataset.flux_t.shape[1])
    corrected, result = lawful, fit_model(lawful, room_field="geometry")
    for _ in range(DRIFT_PASSES):
        used = corrected if result.excluded is None else corrected.select(~result.excluded)  # as the fit
        step = fit_drift(used, result.model, temperature.mean_c)
        drift = drift + step
        corrected = replace(
            dataset, flux_t=to_reference(dataset.flux_t, celsius, temperature.mean_c, laws, drift)
        )
        if np.linalg.norm(step) <= DRIFT_SETTLED * np.linalg.norm(drift):
            break
        result = fit_model(corrected, room_field="geometry")
    # The no-load poses judge the room only once the drift has settled: before, they still
    # carry the part the fit absorbed, a 4th direction that is no field's.
    return corrected, replace(temperature, drift_t_per_k=drift), fit_model(corrected)
