"""A rate picked by accuracy: `ftsensord set --accuracy` and a sensor table's ``accuracy`` key
choose the fastest conversion, averaging and rate whose predicted sigma at rest meets the
target (`processing.accuracy`), or say why none does."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from ftsensord.acquire import choice
from ftsensord.config.accuracy import parse_accuracies, parse_accuracy
from ftsensord.config.file import load_config
from ftsensord.errors import ConfigError
from ftsensord.processing import accuracy as acc
from ftsensord.sim.scene import load_scene
from ftsensord.testing.harness import InProcess

from .test_daemon import Rig, write_config


@pytest.mark.parametrize(
    "text, value, kind",
    [
        ("0.02N", 0.02, "force"),
        ("20 mN", 0.02, "force"),
        ("150uN", 150e-6, "force"),
        ("0.5mNm", 0.5e-3, "torque"),
        ("0.002Nm", 0.002, "torque"),
        ("1e-3 Nm", 1e-3, "torque"),
    ],
)
def test_a_target_is_a_number_and_its_unit(text, value, kind):
    got = parse_accuracy(text)
    assert got.value == pytest.approx(value, rel=1e-12) and got.kind == kind  # a decimal's float: to rounding
    assert got.axes == (slice(0, 3) if kind == "force" else slice(3, 6))


@pytest.mark.parametrize("bad", ["0.02", "0.02 kg", "N", "-1N", "0N", "nanN", 0.02, None, "0.02 N m"])
def test_a_bad_target_names_where_and_what_was_expected(bad):
    with pytest.raises(ConfigError, match=r"^--accuracy: expected a positive number and its unit, N, mN"):
        parse_accuracy(bad, "--accuracy")


def test_one_target_of_each_kind_at_most():
    assert [t.kind for t in parse_accuracies(["0.02N", "1mNm"])] == ["force", "torque"]
    with pytest.raises(ConfigError, match="at most one force and one torque"):
        parse_accuracies(["0.02N", "0.03N"])


@pytest.fixture(scope="module")
def packaged():
    """The packaged simulated configuration: two sensors, their calibrations, untared."""
    config = load_config()
    return config, [acc.Sensor(s, s.estimator) for s in config.sensors]


def worst(sensors, settings, averaging, axes=slice(0, 3), noise=True) -> float:
    """The largest predicted sigma of ``axes`` over the sensors (N or Nm)."""
    return max(
        float(np.max(acc.sigma_at(s, acc.uncertainty_at(s, settings), averaging, noise)[axes]))
        for s in sensors
    )


@pytest.mark.parametrize("axes, unit", [(slice(0, 3), "N"), (slice(3, 6), "Nm")])
def test_the_plan_is_the_fastest_setting_that_meets_the_target(packaged, axes, unit):
    config, sensors = packaged
    bus = config.bus_levers()
    # A target between the running settings' single sample and the floor averaging cannot
    # shrink: met only with some averaging, or a quieter conversion.
    floor = worst(sensors, config.settings, 1, axes, noise=False)
    single = worst(sensors, config.settings, 1, axes)
    target = parse_accuracy(f"{floor + 0.4 * (single - floor):.6g}{unit}")
    targets = {s.config.name: [target] for s in sensors}
    plan = acc.plan(targets, sensors, bus)
    assert all(max(sigma[axes]) <= target.value for sigma in plan.sigma.values())
    assert plan.averaging > 1 or plan.settings != config.settings  # the target asked for something
    # Every other conversion and averaging: none that meets it gives independent samples more often.
    for settings in choice.conversions(config.settings):
        rate = acc.fastest_rate(replace(bus, settings=settings), None, None)
        for averaging in acc.AVERAGINGS:
            if worst(sensors, settings, averaging, axes) <= target.value:
                assert rate / averaging <= plan.effective_hz * (1 + 1e-12), (
                    settings,
                    averaging,
                )  # float ties
                break
    # and the averaging is the least that meets it at the plan's conversion
    assert plan.averaging == 1 or worst(sensors, plan.settings, plan.averaging // 2, axes) > target.value
    # The rate holds with the target spare, as `set` checks it.
    assert plan.rate_hz <= replace(bus, settings=plan.settings).bound("burst", True).rate_hz


def test_a_target_below_what_averaging_can_reach_is_refused_saying_why(packaged):
    config, untared = packaged
    # Tared on 100 samples: the tare's noise is a floor averaging does not shrink.
    sensors = [replace(s, tare_samples=100) for s in untared]
    floor = worst(sensors, config.settings, 1, noise=False)
    assert floor > 0
    target = parse_accuracy(f"{floor / 2:.4g}N")
    with pytest.raises(ConfigError) as exc:
        acc.plan({s.config.name: [target] for s in sensors}, sensors, config.bus_levers())
    text = str(exc.value)
    assert text.startswith(
        f"accuracy: no setting meets sensor1 {target.text}, sensor2 {target.text}: the closest"
    )
    assert f"force {floor:.3g} N" in text and "averaging does not shrink" in text
    # The way out named is what the files hold: the nonlinear estimator's own floor where it is
    # lower (computed, not a guess at more poses), else a larger target.
    nonlinear = [replace(s, estimator="nonlinear") for s in sensors]
    lower = [
        n
        for s, n in zip(sensors, nonlinear)
        if worst([n], config.settings, 1, noise=False) < worst([s], config.settings, 1, noise=False)
    ]
    if lower:
        assert "with the nonlinear estimator (ftsensord set --estimator nonlinear)" in text, text
        assert (
            f"{lower[0].config.name} force {worst([lower[0]], config.settings, 1, noise=False):.3g} N" in text
        )
    else:
        assert text.endswith("a larger target") and "nonlinear" not in text, text


def test_a_target_the_chips_noise_keeps_out_of_reach_says_so(packaged):
    config, sensors = packaged  # untared: at rest the model's error is what the calibration's zero left
    target = parse_accuracy("1e-6N")
    with pytest.raises(ConfigError) as exc:
        acc.plan({s.config.name: [target] for s in sensors}, sensors, config.bus_levers())
    text = str(exc.value)
    if worst(sensors, config.settings, 1, noise=False) < 0.5e-6:
        assert text.endswith(
            f"the chips' noise averaged {acc.MAX_AVERAGING} times stays above it: a larger target"
        )
    else:
        assert "averaging does not shrink" in text, text


def test_set_accuracy_applies_the_fastest_averaging_and_says_the_rate(tmp_path):
    rig = Rig(tmp_path)
    try:
        sensors = [acc.Sensor(p.config, p.estimator, p.tare_samples) for p in rig.daemon.sensors]
        floor = worst(sensors, rig.config.settings, 1, noise=False)
        single = worst(sensors, rig.config.settings, 1)
        text = f"{floor + 0.3 * (single - floor):.5g}N"
        reply = rig.request(cmd="set", accuracy=text)
        assert reply["ok"], reply
        got = reply["result"]
        expected = acc.plan(
            {s.config.name: [parse_accuracy(text)] for s in sensors},
            sensors,
            rig.config.bus_levers(rig.daemon.board_timing),
            rig.config.scheduler,
            settings=[rig.config.settings],
        )
        assert (got["rate_hz"], got["averaging"], got["lowpass_hz"]) == (
            expected.rate_hz,
            expected.averaging,
            0.0,
        )
        assert got["averaging"] > 1 and got["effective_rate_hz"] == pytest.approx(
            expected.effective_hz, abs=1e-3
        )
        assert rig.daemon.period_s == pytest.approx(1 / expected.rate_hz)
        # status then predicts what was asked for
        status = rig.request(cmd="status")["result"]["sensors"]
        assert all(max(s["sigma"]["sigma"][:3]) <= float(text[:-1]) for s in status.values())
        assert len(rig.cycles(5)["wrench/sensor1"]) == 5
    finally:
        rig.close()


@pytest.mark.parametrize(
    "args, error",
    [
        ({"accuracy": "0.02"}, "accuracy: expected a positive number and its unit"),
        ({"accuracy": "1e-6N"}, "accuracy: no setting meets sensor1 1e-6N"),
        ({"accuracy": "0.05N", "averaging": 2}, "accuracy: set it in a request of its own"),
    ],
)
def test_a_bad_or_unmeetable_accuracy_is_an_error_reply_and_nothing_changes(tmp_path, args, error):
    rig = Rig(tmp_path)
    try:
        before = rig.daemon.config.rate_hz, rig.daemon.config.averaging, rig.daemon.config.lowpass_hz
        reply = rig.request(cmd="set", **args)
        assert reply["ok"] is False and error in reply["error"], reply
        assert (
            rig.daemon.config.rate_hz,
            rig.daemon.config.averaging,
            rig.daemon.config.lowpass_hz,
        ) == before
        assert len(rig.cycles(2)["wrench/sensor1"]) == 2  # and the daemon goes on
    finally:
        rig.close()


def accuracy_config(tmp_path, sensor1: str) -> object:
    """`write_config`'s file with ``accuracy = <sensor1>`` in sensor1's table."""
    path = write_config(tmp_path)
    path.write_text(path.read_text().replace('name = "sensor1"', f'name = "sensor1"\naccuracy = {sensor1}'))
    return path


def test_a_sensors_accuracy_key_chooses_the_conversion_averaging_and_rate_at_start(tmp_path):
    base = load_config(write_config(tmp_path))
    sensors = [acc.Sensor(s, s.estimator) for s in base.sensors]
    floor = worst(sensors[:1], base.settings, 1, noise=False)
    single = worst(sensors[:1], base.settings, 1)
    text = f"{floor + 0.3 * (single - floor):.5g}N"
    config = load_config(accuracy_config(tmp_path, f'["{text}", "50mNm"]'))
    assert [t.text for t in config.sensors[0].accuracy] == [text, "50mNm"] and config.sensors[
        1
    ].accuracy == ()
    expected = acc.plan(
        {"sensor1": list(config.sensors[0].accuracy)},
        [acc.Sensor(s, s.estimator) for s in config.sensors],
        config.bus_levers(),
    )
    planned = acc.apply_accuracy(config)
    assert planned == expected
    assert (config.settings, config.rate_hz, config.averaging, config.lowpass_hz) == (
        expected.settings,
        expected.rate_hz,
        expected.averaging,
        0.0,
    )
    assert "accuracy" not in config.choice  # the scheduler chosen for that rate, holding it
    # A daemon on it runs those settings, and a reload of the same file keeps them (it plans again).
    d = InProcess(config, load_scene(tmp_path / "scene.toml"))
    try:
        assert d.daemon.config.averaging == expected.averaging
        reply = Rig.request(d, cmd="reload")  # type: ignore[arg-type]  # Rig's request: InProcess has its socket
        assert reply["ok"], reply
        assert (d.daemon.config.settings, d.daemon.config.averaging) == (
            expected.settings,
            expected.averaging,
        )
    finally:
        d.close()


@pytest.mark.parametrize("value", ['"0.02"', "0.02", '["0.02N", "0.03N"]'])
def test_a_bad_accuracy_key_names_the_file_and_the_key(tmp_path, value):
    path = accuracy_config(tmp_path, value)
    with pytest.raises(ConfigError) as exc:
        load_config(path)
    assert str(exc.value).startswith(
        f"{path}: sensor[0].accuracy: expected a positive number and its unit"
    ), exc.value


@pytest.mark.parametrize(
    "args, said",
    [
        (["--accuracy", "0.02N", "--rate", "50"], "set: --accuracy goes alone"),
        (["--accuracy", "0.02"], "--accuracy: expected a positive number and its unit"),
    ],
)
def test_the_command_line_refuses_a_bad_accuracy_before_asking_the_daemon(tmp_path, args, said):
    import subprocess
    import sys

    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "ftsensord",
            "set",
            *args,
            "--control",
            f"ipc://{tmp_path}/nobody",
            "--timeout",
            "0.5",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 2 and said in done.stderr, done.stderr


def test_doctor_with_a_configuration_shows_each_sensors_predicted_sigma(tmp_path):
    import json
    import subprocess
    import sys

    path = write_config(tmp_path, extra="averaging = 4")
    done = subprocess.run(
        [sys.executable, "-m", "ftsensord", "doctor", "--json", "--config", str(path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode in (0, 2), done.stderr  # 2: the simulated chips' occasional errors, a warning
    got = json.loads(done.stdout)["predicted_sigma"]
    config = load_config(path)
    assert (got["averaging"], got["osr"], got["dig_filt"]) == (
        4,
        config.settings.osr,
        config.settings.dig_filt,
    )
    for s in config.sensors:
        sensor = acc.Sensor(s, s.estimator)
        expected = acc.sigma_at(sensor, acc.uncertainty_at(sensor, config.settings), 4)
        np.testing.assert_allclose(
            got["sensors"][s.name]["sigma"], expected, atol=1e-7
        )  # status's 7 decimals


def test_set_says_when_another_conversion_would_meet_it_faster_after_a_restart(tmp_path):
    from types import SimpleNamespace

    from ftsensord.cli.service import faster_conversion

    path = write_config(tmp_path)
    status = {"config": str(path), "sensors": {"sensor1": {"estimator": "linear"}, "sensor2": {}}}
    control = SimpleNamespace(status=lambda: status)
    config = load_config(path)
    sensors = [acc.Sensor(s, s.estimator) for s in config.sensors]
    floor = worst(sensors, config.settings, 1, noise=False)
    single = worst(sensors, config.settings, 1)
    text = f"{floor + 0.3 * (single - floor):.5g}N"
    best = acc.plan({s.config.name: [parse_accuracy(text)] for s in sensors}, sensors, config.bus_levers())
    said = faster_conversion(control, [text], best.effective_hz / 2)
    assert said is not None and said.startswith(
        f"faster with a restart: [chip] osr = {best.settings.osr}, dig_filt = {best.settings.dig_filt} "
        f"gives {best.rate_hz:g} Hz with averaging {best.averaging}"
    )
    assert faster_conversion(control, [text], best.effective_hz) is None  # already the fastest
    status["config"] = str(tmp_path / "elsewhere.toml")  # a file this host cannot read: nothing said
    assert faster_conversion(control, [text], 1.0) is None
