"""One string chooses the bus; scene files; the scan command."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ftsensord.acquire.bus import open_bus, parse_bus_spec
from ftsensord.acquire.scan import scan
from ftsensord.chip import mlx90393 as mlx
from ftsensord.cli import main
from ftsensord.errors import ConfigError
from ftsensord.sim import (
    PhysicalScene,
    SimulatedBus,
    default_scene,
    load_scene,
    two_sensor_scene,
)

from .conftest import assert_names_file_and_key

SCENE = """\
version = 1
kind = "static"
temperature_c = 22.0

[[chip]]
address = 0x0D
field_ut = [10.0, -20.0, 1500.0]

[[chip]]
address = 0x1A
field_ut = [0.0, 0.0, -900.0]
temperature_c = 40.0
"""


@pytest.mark.parametrize(
    ("spec", "parsed"),
    [
        ("sim", ("sim", None)),
        ("sim:scenes/a.toml", ("sim", "scenes/a.toml")),
        ("i2c:1", ("i2c", "1")),
        ("i2c:/dev/i2c-3", ("i2c", "/dev/i2c-3")),
    ],
)
def test_accepted_bus_specs(spec, parsed):
    assert parse_bus_spec(spec) == parsed


@pytest.mark.parametrize("spec", ["", "i2c", "i2c:", "i2c:one", "spi:0", "sim:", "SIM", None, 1])
def test_a_bad_bus_spec_names_the_accepted_forms(spec):
    with pytest.raises(ConfigError, match="i2c:<N>.*sim:<scene file>"):
        open_bus(spec)


def test_sim_options_are_refused_for_a_real_bus():
    with pytest.raises(ConfigError, match="simulated bus only"):
        open_bus("i2c:1", bus_hz=400e3)


def test_sim_opens_the_default_scene_of_16_chips():
    bus = open_bus("sim")
    assert isinstance(bus, SimulatedBus)
    assert sorted(bus.chips) == list(range(0x0C, 0x1C))


def test_the_nominal_scene_is_two_symmetric_sensors_at_rest():
    scene = two_sensor_scene()
    assert [s.name for s in scene.sensors] == ["sensor1", "sensor2"] and not scene.external_field_t.any()
    bz = np.array([scene.field_t(a, 0.0)[2] for a in scene.addresses])
    # Every chip sees the same field at rest (the ring is symmetric): its magnet
    # 6 mm away plus its neighbours' crosstalk, inside GAIN_SEL 0 RES 3's range.
    assert np.allclose(bz, bz[0]) and 1.0e-3 < bz[0] < 2.0e-3
    # config/scene-nominal.toml is the same scene, for the command line.
    from_file = load_scene(Path(__file__).resolve().parent.parent / "config" / "scene-nominal.toml")
    assert np.array_equal(
        [from_file.field_t(a, 0.0) for a in scene.addresses], [scene.field_t(a, 0.0) for a in scene.addresses]
    )


def test_the_default_scene_is_two_as_built_sensors_at_rest_in_the_earths_field():
    scene, nominal = default_scene(), two_sensor_scene()
    assert isinstance(scene, PhysicalScene) and [s.name for s in scene.sensors] == ["sensor1", "sensor2"]
    assert 45e-6 < np.linalg.norm(scene.external_field_t) < 50e-6 and scene.external_field_t[2] < -40e-6
    b = np.array([scene.field_t(a, 0.0) for a in scene.addresses])
    b_nominal = np.array([nominal.field_t(a, 0.0) for a in scene.addresses])
    # Each chip's own part (magnet placement and remanence, tilt, gain): the chips no longer
    # read alike, by tens of uT to a few hundred, and both parts differ; all in range still.
    off = np.linalg.norm(b - b_nominal, axis=1)
    assert np.all(off > 10e-6) and np.all(off < 0.5e-3) and not np.allclose(off[:8], off[8:])
    assert np.all((1.0e-3 < b[:, 2]) & (b[:, 2] < 2.0e-3))


def test_scene_file_loads(tmp_path):
    path = tmp_path / "two.toml"
    path.write_text(SCENE)
    scene = load_scene(path)
    assert scene.addresses == (0x0D, 0x1A)
    assert np.allclose(scene.field_t(0x0D, 0.0), [10e-6, -20e-6, 1500e-6])
    assert scene.temperature_c(0x0D, 0.0) == 22.0 and scene.temperature_c(0x1A, 0.0) == 40.0


@pytest.mark.parametrize(
    ("edit", "key", "expected"),
    [
        (("version = 1", "version = 2"), "version", "expected 1"),
        (('kind = "static"', 'kind = "magic"'), "kind", 'expected one of "static", "sensors"'),
        (("address = 0x0D", "address = 0x0B"), "chip[0].address", "0x0C-0x1B"),
        (("address = 0x1A", "address = 0x0D"), "chip[1].address", "not used before"),
        (("[10.0, -20.0, 1500.0]", "[10.0, 1500.0]"), "chip[0].field_ut", "3 finite numbers"),
        (("[10.0, -20.0, 1500.0]", "[10.0, nan, 1500.0]"), "chip[0].field_ut", "3 finite numbers"),
        (("temperature_c = 40.0", 'temperature_c = "hot"'), "chip[1].temperature_c", "finite number"),
        (("temperature_c = 40.0", "colour = 1"), "chip[1].colour", "one of address"),
        (("temperature_c = 22.0", "temprature_c = 22.0"), "temprature_c", "one of"),
        (("[[chip]]", "[chips]"), "chips", "one of"),
        (("version = 1", "version = = 1"), "not valid TOML", ""),
    ],
)
def test_a_bad_scene_file_names_the_file_the_key_and_what_was_expected(tmp_path, edit, key, expected):
    path = tmp_path / "bad.toml"
    path.write_text(SCENE.replace(*edit, 1))
    assert_names_file_and_key(load_scene, path, key, expected)


def test_a_missing_scene_file_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="nope.toml: cannot read"):
        open_bus(f"sim:{tmp_path / 'nope.toml'}")


# --- scan ----------------------------------------------------------------------------
def test_scan_finds_the_default_16_chips_with_variants_registers_and_readings(capsys):
    assert main(["scan", "--bus", "sim", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    chips = out["chips"]
    assert [c["address"] for c in chips] == [f"0x{a:02X}" for a in range(0x0C, 0x1C)]
    assert [c["part"][-3:] for c in chips] == ["011"] * 4 + ["012"] * 4 + ["013"] * 4 + ["014"] * 4
    scene = default_scene()
    for c in chips:
        assert c["registers"] == {"0x00": "0x007C", "0x01": "0x0000", "0x02": "0x0000"}  # as found
        assert c["found_settings"]["GAIN_SEL"] == 7
        truth = scene.field_t(int(c["address"], 16), 0.0) * 1e6
        # Within 5 sigma of the noise (2 uT X/Y, 3 uT Z) plus one LSB (6.0 / 9.7 uT).
        assert np.allclose(c["field_ut"], truth, atol=[16.1, 16.1, 24.7])
        assert c["temperature_c"] == pytest.approx(25.0, abs=0.5)
        assert c["error"] is None and c["saturated"] == [False, False, False]


def test_scan_of_a_scene_file_finds_its_chips_and_prints_a_table(tmp_path, capsys):
    path = tmp_path / "two.toml"
    path.write_text(SCENE)
    assert main(["scan", "--bus", f"sim:{path}"]) == 0
    out = capsys.readouterr().out
    lines = out.strip().splitlines()
    assert lines[1].startswith("0x0D  MLX90393SLW-ABA-011") and lines[2].startswith(
        "0x1A  MLX90393SLW-ABA-014"
    )
    assert "2 chip(s) found" in lines[-1]
    assert float(lines[2].split()[8]) == pytest.approx(40.0, abs=0.5)  # T/degC column


def test_scan_reports_a_chip_that_fails_midway_and_goes_on():
    bus = open_bus("sim")
    bus.chips[0x10].memory_error = True  # ACKs but refuses every command but RT
    bus.detach(0x11)
    bus.chips[0x12].drift_register(mlx.REG_CONF3, 0, at=0.0)  # harmless: configure rewrites it
    reports = {r.address: r for r in scan(bus)}
    assert 0x11 not in reports and len(reports) == 15
    assert "refused" in reports[0x10].error and reports[0x10].measurement is None
    assert all(r.error is None and r.measurement is not None for a, r in reports.items() if a != 0x10)


def test_scan_exit_codes_on_errors(capsys):
    assert main(["scan", "--bus", "nonsense"]) == 2
    assert "accepted forms" in capsys.readouterr().err
    assert main(["scan", "--bus", "i2c:/dev/i2c-does-not-exist"]) == 2
    assert (
        "does not exist" in capsys.readouterr().err
    )  # and how a board gets it: test_a_missing_i2c_device_names_the_fix


def test_console_entry_point_runs_as_a_module():
    out = subprocess.run(
        [sys.executable, "-m", "ftsensord", "scan", "--bus", "sim"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-1] == "16 chip(s) found on sim"


def test_the_example_scene_in_config_loads_and_shows_a_saturated_chip():
    path = Path(__file__).resolve().parent.parent / "config" / "scene-static.toml"
    reports = {r.address: r for r in scan(open_bus(f"sim:{path}"))}
    assert sorted(reports) == [0x0C, 0x0D, 0x14]
    assert list(reports[0x14].measurement.saturated) == [False, False, True]
    assert not reports[0x0D].measurement.any_saturated


def test_dataset_and_calibrate_commands(tmp_path, capsys):
    ds, cal, rep = tmp_path / "ds.json", tmp_path / "cal.json", tmp_path / "report.md"
    # The default scene is a room: the fit needs no-load poses to measure its field, and
    # enough readings a pose that their noise floor is seen (2 often quantise alike).
    assert (
        main(
            [
                "dataset",
                "-o",
                str(ds),
                "--poses",
                "40",
                "--validation-poses",
                "10",
                "--samples",
                "5",
                "--no-load-poses",
                "12",
                "--hold-s",
                "0",
            ]
        )
        == 0
    )  # a spring: no step-and-hold to pay for
    assert "86 poses (six-axis)" in capsys.readouterr().out  # 40 fit, 10 validation, 12 no-load, 24 check
    assert main(["calibrate", str(ds), "-o", str(cal), "--report", str(rep), "--serial", "SN-1"]) == 0
    out = capsys.readouterr().out
    assert "validation RMSE: Fx" in out and "isotropy" in out
    from ftsensord.calibration.calfile import Calibration

    loaded = Calibration.load(cal)
    assert loaded.serial == "SN-1" and loaded.addresses == tuple(range(0x0C, 0x14))
    text = rep.read_text()
    assert "paper, Table II" in text and "this calibration" in text and "ftsensord calibrate" in text


def test_calibrate_refuses_the_one_arm_plan_with_the_reason(tmp_path, capsys):
    ds = tmp_path / "one.json"
    assert (
        main(
            [
                "dataset",
                "-o",
                str(ds),
                "--plan",
                "one-arm",
                "--poses",
                "30",
                "--validation-poses",
                "0",
                "--samples",
                "1",
                "--no-sweep",
                "--hold-s",
                "0",
            ]
        )
        == 0
    )
    capsys.readouterr()
    assert main(["calibrate", str(ds), "-o", str(tmp_path / "cal.json")]) == 2
    err = capsys.readouterr().err
    assert "Mz is not excited" in err and "lever arm points off the shaft axis" in err
    assert not (tmp_path / "cal.json").exists()


def test_dataset_refuses_a_static_scene_and_an_unknown_sensor(tmp_path, capsys):
    scene = tmp_path / "s.toml"
    scene.write_text(SCENE)
    assert main(["dataset", "-o", str(tmp_path / "d.json"), "--scene", str(scene)]) == 2
    assert 'kind "sensors"' in capsys.readouterr().err
    assert main(["dataset", "-o", str(tmp_path / "d.json"), "--sensor", "sensor9"]) == 2
    assert "sensor1, sensor2" in capsys.readouterr().err


# --- a board whose I2C is off: the first command a Pi user runs says what to do ------------
@pytest.mark.parametrize("command", ["scan", "doctor"])
def test_a_missing_i2c_device_names_the_fix(command, capsys):
    """No /dev/i2c-N (I2C off in config.txt, or i2c-dev not loaded): the message names the
    switches that turn it on, not only the errno."""
    assert main([command, "--bus", "i2c:/dev/i2c-97"]) == 2
    err = capsys.readouterr().err
    assert "/dev/i2c-97" in err and "[Errno" not in err
    for fix in ("raspi-config", "dtparam=i2c_arm=on", "modprobe i2c-dev"):
        assert fix in err, err


def test_a_forbidden_i2c_device_names_the_group(monkeypatch):
    """Permission denied on /dev/i2c-N: the user is not in the i2c group (root is never
    refused, so the kernel's refusal is stood in for at smbus2's open)."""
    from ftsensord.acquire import bus as busmod

    def refuse(device):
        raise PermissionError(13, "Permission denied", "/dev/i2c-1")

    monkeypatch.setattr(busmod, "SMBus", refuse)
    with pytest.raises(busmod.BusUnavailableError, match=r"usermod -aG i2c") as info:
        open_bus("i2c:1")
    assert info.value.errno == 13 and isinstance(info.value, OSError)
