"""A warming sensor (issue 23): per-sensor temperature profiles acting on the magnets, the
silicone and each chip's sensitivity and offset, read back on the chips' T channel."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ftsensord.calibration.dataset import Dataset
from ftsensord.calibration.procedure import simulate_dataset
from ftsensord.chip import mlx90393 as mlx
from ftsensord.chip.driver import MLX90393
from ftsensord.model.magnet import NDFEB_BR_TEMPCO_PER_K, remanence_factor
from ftsensord.model.silicone import STIFFNESS_TEMPCO_PER_K, stiffness_factor
from ftsensord.sim import (
    NOISELESS,
    EmulatedMLX90393,
    SimulatedBus,
    StaticScene,
    VirtualClock,
    load_scene,
    simulated_bus,
)
from ftsensord.sim import physics as sim_physics
from ftsensord.sim.heat import ChipDrift, TemperatureProfile
from ftsensord.sim.loads import StaticLoad
from ftsensord.sim.physics import PhysicalScene, SimSensor, Tolerances
from ftsensord.sim.scene import TEMPERATURE_RANGE_C, default_scene_path

from .conftest import assert_names_file_and_key

CONFIG = Path(__file__).resolve().parent.parent / "config"
#: 25 degC, then 10 K warmer over 100 s, then held: the shape of config/scene-warm.toml.
WARMING = TemperatureProfile((0.0, 20.0, 120.0), (25.0, 25.0, 35.0))
ADDRESSES = tuple(range(0x0C, 0x14))


def one_sensor(temperature: TemperatureProfile | None = None, **options) -> PhysicalScene:
    return PhysicalScene([SimSensor("s", ADDRESSES, temperature=temperature, **options)])


def test_the_profile_interpolates_holds_its_ends_and_refuses_bad_times():
    assert [WARMING.at(t) for t in (-1.0, 10.0, 20.0, 70.0, 120.0, 500.0)] == [25, 25, 25, 30, 35, 35]
    assert TemperatureProfile.linear(20.0, 0.5).at(4.0) == 22.0
    assert TemperatureProfile.constant(25.0).is_reference and not WARMING.is_reference
    with pytest.raises(ValueError, match="strictly increasing"):
        TemperatureProfile((0.0, 0.0), (25.0, 26.0))


def test_the_magnets_of_each_sensor_follow_its_own_profile():
    scene = PhysicalScene(
        [SimSensor("warm", ADDRESSES, temperature=WARMING), SimSensor("cool", tuple(range(0x14, 0x1C)))],
        temperature_c=25.0,
    )
    for t, celsius in ((70.0, 30.0), (300.0, 35.0)):
        ratio = scene.field_t(0x0C, t) / scene.field_t(0x0C, 0.0)
        # At rest, in a field-free room, every field is the magnets': it scales with Br alone.
        assert ratio == pytest.approx(np.full(3, 1 + NDFEB_BR_TEMPCO_PER_K * (celsius - 25)), rel=1e-12)
        assert np.array_equal(scene.field_t(0x14, t), scene.field_t(0x14, 0.0))  # the other one stays
    assert sim_physics.NDFEB_BR_TEMPCO_PER_K == NDFEB_BR_TEMPCO_PER_K  # sim's old name still works


@pytest.mark.parametrize("stiffening", [0.0, 0.3])
def test_warm_silicone_deflects_less_under_the_same_load(stiffening):
    load = StaticLoad(np.array([20.0, -10.0, 8.0, 0.05, -0.08, 0.1]))
    warm = one_sensor(TemperatureProfile.constant(35.0), stiffening=stiffening, load=load)
    cold = one_sensor(stiffening=stiffening)
    # K(35 degC) = K (1 + 10 / 298.15): the warm sensor under w is the cold one under w / that.
    cold.set_load(0, StaticLoad(load.wrench(0.0) / stiffness_factor(10.0)))
    for a in ADDRESSES:
        assert warm.field_t(a, 0.0) == pytest.approx(remanence_factor(10.0) * cold.field_t(a, 0.0), rel=1e-12)
    xi_cold, xi_warm = (
        warm.sensors[0].deflection(load.wrench(0.0) / f) for f in (1.0, stiffness_factor(10.0))
    )
    assert np.linalg.norm(xi_warm) < np.linalg.norm(xi_cold)
    assert STIFFNESS_TEMPCO_PER_K == pytest.approx(1 / 298.15)  # entropic: stiffer by T in kelvin


def chip_bus(temperature_c: float, drift: ChipDrift, field_ut=(3000.0, -2000.0, 9000.0)):
    """One emulated chip drifting by ``drift``, at a fixed field and die temperature."""
    scene = StaticScene({0x0C: np.array(field_ut) * 1e-6}, {0x0C: temperature_c})
    chip = EmulatedMLX90393(0x0C, scene, noise=NOISELESS, drift=drift)
    bus = SimulatedBus([chip], clock=VirtualClock())
    return bus, MLX90393(bus, 0x0C, sleep=bus.sleep)


@pytest.mark.parametrize("tcmp", [False, True])
def test_the_chip_drifts_by_its_own_tcmp_en(tcmp):
    drift = ChipDrift(
        np.array([-4e-3, -5e-3, -6e-3]), np.array([4e-4, -3e-4, 1e-4]), np.array([2e-6, -2.5e-6, 4e-6])
    )
    # TCMP_EN = 1 allows RES 0 and 1 only; RES 0 at GAIN_SEL 0 is 0.751 uT/LSB (X/Y).
    settings = mlx.Settings(res_x=0, res_y=0, res_z=0, tcmp_en=tcmp)
    field = np.array([3000.0, -2000.0, 9000.0]) * 1e-6
    readings = {}
    for celsius in (25.0, 45.0):
        bus, drv = chip_bus(celsius, drift)
        drv.reset()
        drv.configure(settings)
        readings[celsius] = drv.measure().field_t
    lsb = np.array([settings.sensitivity_ut(a) for a in "xyz"]) * 1e-6
    sensitivity = drift.sensitivity_tcmp_per_k if tcmp else drift.sensitivity_per_k
    expected = field * (1 + 20.0 * sensitivity) + 20.0 * drift.offset_t_per_k
    assert np.all(np.abs(readings[25.0] - field) <= lsb / 2)  # at 25 degC nothing drifts
    assert np.all(np.abs(readings[45.0] - expected) <= lsb / 2)  # quantised to the LSB, nothing else
    other = drift.sensitivity_per_k if tcmp else drift.sensitivity_tcmp_per_k
    assert np.all(np.abs(field * (1 + 20.0 * other) + 20.0 * drift.offset_t_per_k - readings[45.0]) > lsb)


def test_chip_drifts_are_drawn_after_the_old_draws_within_the_datasheets_spread():
    tol = Tolerances(0.15e-3, 0.03, np.radians(1.5), 0.02, 0.1e-3, seed=7)
    geometry, gains, drifts = tol.build_part()
    old_geometry, old_gains = tol.build()
    assert np.array_equal(gains, old_gains) and np.array_equal(geometry.magnet_p, old_geometry.magnet_p)
    sens = np.array([d.sensitivity_per_k for d in drifts])
    tcmp = np.array([d.sensitivity_tcmp_per_k for d in drifts])
    offset = np.array([d.offset_t_per_k for d in drifts])
    # 24 draws each: the TC-off drift within 4 sd of the typical (1 in 15,000 per draw), the
    # others within their bounds, and parts that differ.
    assert np.all(np.abs(sens - mlx.SENSITIVITY_TEMPCO_PER_K) < 4 * mlx.SENSITIVITY_TEMPCO_SPREAD_PER_K)
    assert np.all(np.abs(tcmp) <= mlx.SENSITIVITY_TEMPCO_TCMP_PER_K)
    assert np.all(np.abs(offset) <= np.array(mlx.OFFSET_DRIFT_UT_PER_K) * 1e-6)
    assert len({row.tobytes() for row in sens}) == 8
    again = Tolerances(0.15e-3, 0.03, np.radians(1.5), 0.02, 0.1e-3, seed=7).build_part()[2]
    assert all(np.array_equal(a.offset_t_per_k, b.offset_t_per_k) for a, b in zip(drifts, again))
    # Without tolerances every chip takes the datasheet's figures.
    assert np.array_equal(one_sensor().chip_drift(0x0C).sensitivity_per_k, mlx.SENSITIVITY_TEMPCO_PER_K)


def words(scene, times: list[float]) -> list[dict[int, tuple[float, ...]]]:
    """Every chip's X, Y, Z, T through the driver at ``times`` (s), with the default noise."""
    bus = simulated_bus(scene, clock=VirtualClock(), seed=3)
    drivers = [MLX90393(bus, a, sleep=bus.sleep) for a in scene.addresses]
    for d in drivers:
        d.reset()
        d.configure(mlx.Settings())
    out = []
    for t in times:
        bus.sleep(t - (bus.clock.now() - bus.epoch))
        measured = {d.address: d.measure(mlx.ZYXT_XYZT) for d in drivers}
        out.append({a: (*m.field_t, m.temperature_c) for a, m in measured.items()})
    return out


def test_a_scene_held_at_25_degc_reads_exactly_as_today(tmp_path):
    today = default_scene_path().read_text()
    held = today.replace("seed = 1", 'seed = 1\n[sensor.temperature]\nkind = "constant"\ncelsius = 25.0', 1)
    assert held != today
    (tmp_path / "held.toml").write_text(held)
    times = [0.5, 1.0, 2.0]
    assert words(load_scene(tmp_path / "held.toml"), times) == words(load_scene(default_scene_path()), times)
    # config/scene-warm.toml is the default scene until it starts warming at 20 s.
    assert words(load_scene(CONFIG / "scene-warm.toml"), times) == words(
        load_scene(default_scene_path()), times
    )


def test_the_die_temperature_read_through_the_driver_follows_the_profile():
    scene = load_scene(CONFIG / "scene-warm.toml")
    bus = simulated_bus(scene, clock=VirtualClock(), noise=NOISELESS)
    drivers = [MLX90393(bus, a, sleep=bus.sleep) for a in (0x0C, 0x1B)]
    for d in drivers:
        d.reset()
        d.configure(mlx.Settings())
    for t, celsius in ((10.0, 25.0), (50.0, 27.5), (80.0, 30.0), (140.0, 35.0), (200.0, 35.0)):
        bus.sleep(t - (bus.clock.now() - bus.epoch))
        for d in drivers:
            # The conversion ends within a few ms of t (0.3 mK at 10 K / 120 s); the word is
            # 1/45.2 degC.
            assert d.measure(mlx.ZYXT_XYZT).temperature_c == pytest.approx(celsius, abs=0.5 / 45.2 + 1e-3)


TEMPERATURE_SCENE = """\
version = 1
kind = "sensors"

[[sensor]]
addresses = [0x0C, 0x0D, 0x0E, 0x0F, 0x10, 0x11, 0x12, 0x13]
[sensor.temperature]
kind = "recorded"
times_s = [0.0, 20.0, 140.0]
celsius = [25.0, 25.0, 35.0]
"""


@pytest.mark.parametrize(
    ("edit", "key", "expected"),
    [
        (
            ('kind = "recorded"', 'kind = "ramp"'),
            "sensor[0].temperature.kind",
            '"constant", "linear", "recorded"',
        ),
        (
            ("times_s = [0.0, 20.0, 140.0]", "times_s = [0.0, 140.0, 20.0]"),
            "sensor[0].temperature.times_s",
            "strictly increasing",
        ),
        (("times_s = [0.0, 20.0, 140.0]", "times_s = []"), "sensor[0].temperature.times_s", "at least one"),
        (
            ("celsius = [25.0, 25.0, 35.0]", "celsius = [25.0, 35.0]"),
            "sensor[0].temperature.celsius",
            "3 finite numbers (degC, one per time",
        ),
        (
            ("celsius = [25.0, 25.0, 35.0]", "celsius = [25.0, 25.0, 308.15]"),
            "sensor[0].temperature.celsius",
            "temperatures in [-20.0, 85.0]",
        ),
        (('kind = "recorded"', 'kind = "constant"'), "sensor[0].temperature.times_s", "one of celsius, kind"),
        (
            (
                'kind = "recorded"\ntimes_s = [0.0, 20.0, 140.0]\ncelsius = [25.0, 25.0, 35.0]',
                'kind = "constant"\ncelsius = 400',
            ),
            "sensor[0].temperature.celsius",
            "finite number in [-20.0, 85.0]",
        ),
        (
            (
                'kind = "recorded"\ntimes_s = [0.0, 20.0, 140.0]\ncelsius = [25.0, 25.0, 35.0]',
                'kind = "linear"\ncelsius = 25.0',
            ),
            "sensor[0].temperature.drift_c_per_s",
            "missing",
        ),
        (
            (
                '[sensor.temperature]\nkind = "recorded"\ntimes_s = [0.0, 20.0, 140.0]\ncelsius = [25.0, 25.0, 35.0]',
                "temperature = 30",
            ),
            "sensor[0].temperature",
            "a table",
        ),
    ],
)
def test_a_bad_temperature_table_names_file_key_and_expectation(tmp_path, edit, key, expected):
    path = tmp_path / "bad.toml"
    text = TEMPERATURE_SCENE.replace(*edit, 1)
    assert text != TEMPERATURE_SCENE
    path.write_text(text)
    assert_names_file_and_key(load_scene, path, key, expected)


@pytest.mark.parametrize(
    ("text", "key"),
    [
        (
            TEMPERATURE_SCENE.replace('kind = "sensors"', 'kind = "sensors"\ntemperature_c = 298.15'),
            "temperature_c",
        ),
        (
            'version = 1\nkind = "static"\ntemperature_c = 298.15\n[[chip]]\naddress = 0x0C\nfield_ut = [1, 2, 3]\n',
            "temperature_c",
        ),
        (
            'version = 1\nkind = "static"\n[[chip]]\naddress = 0x0C\nfield_ut = [1, 2, 3]\ntemperature_c = -30\n',
            "chip[0].temperature_c",
        ),
    ],
)
def test_every_scene_temperature_is_in_the_chips_operating_range(tmp_path, text, key):
    """A kelvin figure (298.15) or a temperature the parts are not specified at, written in
    any of a scene's temperature keys, is refused as in ``[sensor.temperature]``: before,
    the scene-wide and the static scene's keys took any number, and the chips read 298 degC."""
    path = tmp_path / "bad.toml"
    path.write_text(text)
    assert_names_file_and_key(
        load_scene, path, key, f"in [{mlx.OPERATING_RANGE_C[0]}, {mlx.OPERATING_RANGE_C[1]}]"
    )


def test_a_dataset_recorded_at_the_scenes_coldest_loads_for_calibration(tmp_path):
    """What a scene may hold, the calibration takes: a sensor at the low end of the chips'
    range gives a dataset `Dataset.load` reads back (before, a scene took -40 degC and the
    dataset file refused anything below -20, so `ftsensord calibrate` refused what
    `ftsensord dataset` had written)."""
    low = TEMPERATURE_RANGE_C[0]  # the coldest a scene file takes
    scene = PhysicalScene([SimSensor("s", ADDRESSES, temperature=TemperatureProfile.constant(low + 0.2))])
    ds = simulate_dataset(
        scene, "s", "six-axis", poses=30, validation_poses=0, samples=2, seed=1, sweeps=False, no_load_poses=0
    )
    assert ds.temperature_c is not None and ds.temperature_c.min() < low + 0.5
    ds.save(tmp_path / "cold.json")
    assert np.array_equal(Dataset.load(tmp_path / "cold.json").temperature_c, ds.temperature_c)


def test_the_warm_scene_file_warms_both_sensors_whose_chips_drift_as_their_parts():
    path = CONFIG / "scene-warm.toml"
    scene = load_scene(path)
    assert isinstance(scene, PhysicalScene)
    assert [scene.temperature_c(a, 80.0) for a in (0x0C, 0x1B)] == [30.0, 30.0]
    # The chips are the parts of seeds 1 and 2 (drawn, not typical), different from each other.
    assert not np.array_equal(scene.chip_drift(0x0C).offset_t_per_k, scene.chip_drift(0x14).offset_t_per_k)
