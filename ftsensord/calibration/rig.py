"""The calibration rig: recording a dataset from a bus, and the simulated stage sweep.

`record_dataset` reads the chips through the same driver the daemon uses, so a
simulated run (the scene applies the load) and a real one (a robot applies it)
produce the same `Dataset`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from ftsensord.calibration.dataset import Dataset, Hold, Sweep
from ftsensord.chip import mlx90393 as mlx
from ftsensord.chip.driver import MLX90393
from ftsensord.chip.i2c import Bus
from ftsensord.model.geometry import SensorGeometry
from ftsensord.model.magnet import cylinder_field, dipole_field
from ftsensord.sim.chip import NoiseModel
from ftsensord.sim.loads import CalibrationPose, FixedOrientation, StaticLoad
from ftsensord.sim.physics import PhysicalScene


def record_dataset(
    bus: Bus,
    addresses: Sequence[int],
    poses: Sequence[tuple[CalibrationPose, str]],
    apply_load: Callable[[np.ndarray], None],
    *,
    settings: mlx.Settings = mlx.Settings(),
    samples: int = 100,
    serial: str = "",
    source: str = "",
    turn: Callable[[np.ndarray], None] | None = None,
) -> Dataset:
    """For each pose: turn the sensor (``turn(R_w0)``, when given: the robot's
    orientation, which the room's field sees), apply its wrench, then average
    ``samples`` X, Y, Z readings of every chip: an SM to each chip, the conversion
    time, an RM to each. One write and one read per ioctl: the shape every Linux
    adapter takes (the Pi's i2c-bcm2835 refuses a read that is not last).

    Each pose's full orientation is recorded in the dataset (``rotation``), as a
    real robot knows it from its joints, and its times (``times_s``, the bus's clock from
    the run's start): the load's, and its first and last reading's (the conversions' end):
    what the silicone's creep during each dwell is computed from (`creep.dwell_loads`).
    """
    chips = [MLX90393(bus, a, sleep=bus.sleep) for a in addresses]
    for chip in chips:
        chip.reset()
        chip.configure(settings)
    # +20 %: the chip's oscillator tolerance.
    wait_s = {z: settings.single_measurement_us(z) * 1.2e-6 for z in (mlx.ZYXT_XYZ, mlx.ZYXT_XYZT)}
    n, c = len(poses), len(chips)
    mean, sem = np.zeros((n, 3 * c)), np.zeros((n, 3 * c))
    saturated = np.zeros((n, c), dtype=bool)
    temperature = np.zeros(n)
    times = np.zeros((n, 3))
    start = bus.monotonic()
    for k, (pose, _) in enumerate(poses):
        celsius: list[float] = []
        if turn is not None:
            turn(pose.orientation())
        apply_load(pose.wrench())
        times[k, 0] = bus.monotonic() - start
        readings = np.zeros((samples, 3 * c))
        for s in range(samples):
            # The pose's first and last readings take the die temperature too (their mean is
            # the pose's while it changes steadily): what temperature compensation refers to.
            zyxt = mlx.ZYXT_XYZT if s in (0, samples - 1) else mlx.ZYXT_XYZ
            sampled = bus.monotonic() - start + wait_s[zyxt]  # the conversions' end: the field's time
            times[k, 1] = sampled if s == 0 else times[k, 1]
            times[k, 2] = sampled
            saturated[k] |= _read(bus, chips, zyxt, wait_s[zyxt], readings[s], celsius)
        mean[k] = readings.mean(axis=0)
        temperature[k] = np.mean(celsius)
        if samples > 1:
            sem[k] = readings.std(axis=0, ddof=1) / math.sqrt(samples)
    return Dataset(
        tuple(addresses),
        np.array([p.wrench() for p, _ in poses]),
        mean,
        sem,
        saturated,
        np.array([s for _, s in poses]),
        np.array([p.mass_kg for p, _ in poses]),
        np.array([p.lever_m for p, _ in poses]),
        np.array([p.gravity_dir for p, _ in poses]),
        samples,
        serial,
        source,
        rotation=np.array([p.orientation() for p, _ in poses]),
        temperature_c=temperature,
        times_s=times,
    )


def _read(
    bus: Bus, chips: list[MLX90393], zyxt: int, wait_s: float, out: np.ndarray, celsius: list[float]
) -> np.ndarray:
    """One reading of every chip into ``out`` (T, stacked): an SM to each, the conversion
    time, an RM to each; die temperatures appended to ``celsius``. Returns which saturated."""
    for chip in chips:
        chip.start_single(zyxt)
    bus.sleep(wait_s)
    saturated = np.zeros(len(chips), dtype=bool)
    for i, chip in enumerate(chips):
        m = chip.read_measurement(zyxt)
        out[3 * i : 3 * i + 3] = m.field_t
        saturated[i] = m.any_saturated
        if m.temperature_c is not None:
            celsius.append(m.temperature_c)
    return saturated


def record_hold(
    bus: Bus,
    addresses: Sequence[int],
    poses: Sequence[CalibrationPose],
    apply_load: Callable[[np.ndarray], None],
    *,
    hold_s: float,
    settings: mlx.Settings = mlx.Settings(),
    turn: Callable[[np.ndarray], None] | None = None,
    period_s: float = 0.0,
) -> Hold:
    """The step-and-hold segment (docs/guide/calibration.md): each of ``poses`` in turn, held
    ``hold_s`` while every chip is read every ``period_s`` (0: as fast as the bus allows), each reading stamped
    with the bus's clock (s, from the first pose's start): the creep the silicone's
    relaxation is identified from (`calibration.relaxation`)."""
    chips = [MLX90393(bus, a, sleep=bus.sleep) for a in addresses]
    for chip in chips:
        chip.configure(settings)
    wait_s = settings.single_measurement_us(mlx.ZYXT_XYZ) * 1.2e-6  # +20 %: the oscillator's tolerance
    start = bus.monotonic()
    load_times: list[float] = []
    times: list[float] = []
    rows: list[np.ndarray] = []
    celsius: list[float] = []
    for pose in poses:
        if turn is not None:
            turn(pose.orientation())
        apply_load(pose.wrench())
        load_times.append(bus.monotonic() - start)
        end = load_times[-1] + hold_s
        while (now := bus.monotonic() - start) < end:
            if period_s > 0 and times:
                bus.sleep(max(0.0, times[-1] - wait_s + period_s - now))
                now = bus.monotonic() - start
            row = np.zeros(3 * len(chips))
            if _read(bus, chips, mlx.ZYXT_XYZ, wait_s, row, celsius).any():
                continue  # a clipped reading is no deflection: left out
            times.append(now + wait_s)  # the conversions' end: when the field was sampled
            rows.append(row)
    return Hold(np.array(load_times), np.array([p.wrench() for p in poses]), np.array(times), np.array(rows))


def simulated_robot(scene: PhysicalScene, sensor: str) -> dict[str, Callable[[np.ndarray], None]]:
    """The keyword arguments of `record_dataset` that make a simulated scene's
    sensor do what the calibration robot does to a real one: carry the pose's
    wrench and turn in the room (``apply_load`` and ``turn``)."""
    return {
        "apply_load": lambda w: scene.set_load(sensor, StaticLoad(w)),
        "turn": lambda R: scene.set_orientation(sensor, FixedOrientation(R)),
    }


def simulate_sweeps(
    addresses: Sequence[int],
    geometry: SensorGeometry,
    *,
    field_model: str = "cylinder",
    settings: mlx.Settings = mlx.Settings(),
    noise: NoiseModel = NoiseModel(),
    samples: int = 100,
    span_m: float = 1e-3,
    steps: int = 5,
    rng: np.random.Generator | None = None,
) -> dict[int, Sweep]:
    """The paper's stage experiment, simulated: one magnet moved over a grid of
    +-``span_m`` around its nominal place in each chip's frame, the flux averaged
    over ``samples`` readings (noise of the chip settings, divided by sqrt(samples))."""
    rng = rng if rng is not None else np.random.default_rng(0)
    nominal = geometry.magnet_in_chip()
    offsets = np.linspace(-span_m, span_m, steps)
    grid = np.stack(np.meshgrid(offsets, offsets, offsets, indexing="ij"), axis=-1).reshape(-1, 3)
    sigma = np.array([noise.sigma_ut(a, settings.tconvm_us()) for a in "xyz"]) * 1e-6 / math.sqrt(samples)
    sweeps = {}
    for address, p0 in zip(addresses, nominal):
        positions = p0 + grid
        # The magnet's axis is the chip's z in the stage experiment, as in the sensor.
        if field_model == "dipole":
            flux = dipole_field(-positions, np.array([0.0, 0.0, geometry.magnet_moment_am2]))
        else:
            flux = cylinder_field(
                -positions, geometry.magnet_radius_m, geometry.magnet_length_m, geometry.magnet_br_t
            )
        sweeps[address] = Sweep(positions, flux + rng.normal(0.0, 1.0, flux.shape) * sigma)
    return sweeps
