"""A rate picked by accuracy: `ftsensord set --accuracy` and a sensor table's ``accuracy`` key
choose the fastest conversion, averaging and rate whose predicted sigma at rest meets the
target (`processing.accuracy`), or say why none does."""

from __future__ import annotations

import json
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
        expected = running_plan(rig, text)
        reply = rig.request(cmd="set", accuracy=text)
        assert reply["ok"], reply
        got = reply["result"]
        assert (got["rate_hz"], got["averaging"], got["lowpass_hz"], got["osr"], got["dig_filt"]) == (
            expected.rate_hz,
            expected.averaging,
            0.0,
            expected.settings.osr,
            expected.settings.dig_filt,
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


def running_plan(rig: Rig, text: str) -> acc.Plan:
    """The plan `set --accuracy text` makes on ``rig``'s running daemon: every conversion, its scheduler."""
    d = rig.daemon
    return acc.plan(
        {p.name: [parse_accuracy(text)] for p in d.sensors},
        [acc.Sensor(p.config, p.estimator, p.tare_samples) for p in d.sensors],
        d.config.bus_levers(d.board_timing),
        d.config.scheduler,
        running=d.config.settings,
    )


def at_rest(rig: Rig, n: int = 200) -> tuple[float, np.ndarray, np.ndarray]:
    """Over ``n`` cycles: sensor1's flux noise (its channels' standard deviation, mean, T), its
    mean wrench (N, Nm) and the last published sigma (N, Nm)."""
    got = rig.cycles(n)
    flux = np.array([s.values for s in got["flux/sensor1"]])
    wrench = np.array([s.values for s in got["wrench/sensor1"]])
    return float(flux.std(axis=0).mean()), wrench.mean(axis=0), got["sigma/wrench/sensor1"][-1].values


@pytest.mark.parametrize("scheduler", ["overlapped", "burst"])  # burst: EX before the writes, SB after
def test_set_accuracy_changes_the_chips_conversion_on_the_running_daemon(tmp_path, scheduler):
    from ftsensord.acquire.health import stuck_cycles_for
    from ftsensord.processing.pipeline import channel_sigma_t

    rig = Rig(tmp_path, scheduler=scheduler)
    try:
        d = rig.daemon
        tare(rig)
        noise = {d.config.settings: at_rest(rig)}  # by the conversion running
        tared = {p.name: p.model.zero.copy() for p in d.sensors}
        for text in ("0.03N", "0.2N"):  # a tighter target, then a looser one
            before = d.config.settings
            expected = running_plan(rig, text)
            # the precondition: each target asks for another conversion, the looser a faster one
            assert expected.settings != before
            reply = rig.request(cmd="set", accuracy=text)
            assert reply["ok"] and reply["result"]["conversion_changed"], reply
            new = expected.settings
            assert (reply["result"]["osr"], reply["result"]["dig_filt"]) == (new.osr, new.dig_filt)
            # Every chip holds it (its registers, as the emulated chip reads them), and the reader
            # times its reads and checks its read-backs by it.
            assert {(c.settings().osr, c.settings().dig_filt) for c in rig.bus.chips.values()} == {
                (new.osr, new.dig_filt)
            }
            assert d.reader.settings == d.reader.care.settings == d.config.settings == new
            # stuck_cycles is not in the file: a quieter conversion repeats its words more often
            assert d.reader.care.stuck_cycles == stuck_cycles_for(new)
            assert d.reader.conversion_s(0xE) < d.period_s
            # The pipelines' noise is the new conversion's, the tares held.
            for p in d.sensors:
                np.testing.assert_array_equal(p.sigma_t, channel_sigma_t(new, len(p.config.addresses)))
                assert p.tared
                np.testing.assert_array_equal(p.model.zero, tared[p.name])
            noise[new] = at_rest(rig)
            assert not d.reader.failing  # the read-backs found every chip as written
            status = rig.request(cmd="status")["result"]
            assert (status["osr"], status["dig_filt"]) == (new.osr, new.dig_filt)
            assert all(max(s["sigma"]["sigma"][:3]) <= float(text[:-1]) for s in status["sensors"].values())
            # The measured noise and the published sigma follow the conversion (the averaging
            # stays 1 in both plans: the conversion alone moves them).
            assert expected.averaging == 1
            measured = noise[new][0] / noise[before][0]
            predicted = float(np.mean(channel_sigma_t(new, 1)) / np.mean(channel_sigma_t(before, 1)))
            # Half to twice the predicted change (in log): the words' quantisation (an LSB of
            # 6-10 uT, twice the noise) makes the measured spread follow the noise only roughly.
            assert 0.5 < np.log(measured) / np.log(predicted) < 2, (measured, predicted)
            assert np.all(np.sign(noise[new][2] - noise[before][2]) == np.sign(predicted - 1))
            # The tare holds: at rest the mean wrench stays where it was, within 5 standard errors
            # of the two means' difference (200 samples each; the tare's own error is in both).
            moved = np.abs(noise[new][1] - noise[before][1])
            assert np.all(moved < 5 * np.hypot(noise[new][2], noise[before][2]) / np.sqrt(200)), moved
    finally:
        rig.close()


def tare(rig: Rig) -> None:
    """Tare every sensor on 50 samples, waiting for its reply."""
    rig.req.send(json.dumps({"cmd": "tare", "samples": 50}).encode())
    rig.daemon.handle_control()
    rig.cycles(50)
    assert rig.req.poll(1000) and json.loads(rig.req.recv())["ok"]


def test_a_chip_refusing_the_new_conversion_is_an_error_reply_and_the_daemon_goes_on(tmp_path):
    rig = Rig(tmp_path)
    try:
        d = rig.daemon
        rig.cycles(2)
        before = d.config.settings
        rate, averaging = d.config.rate_hz, d.config.averaging
        rig.bus.faults.nack(0x0E)  # the third chip: the two before it were written
        reply = rig.request(cmd="set", accuracy="0.03N")
        assert reply["ok"] is False, reply
        assert reply["error"].startswith(
            "OSR 2, DIG_FILT 2 not written: MLX90393 at 0x0E: RR failed on the bus"
        )
        assert (
            "that chip is reset and comes back at the running conversion, OSR 1, DIG_FILT 2" in reply["error"]
        )
        assert (d.config.settings, d.reader.settings, d.config.rate_hz, d.config.averaging) == (
            before,
            before,
            rate,
            averaging,
        )
        # Every chip runs the running conversion, or is failing, to be reset to it.
        assert d.reader.failing == {0x0E}
        for a, chip in rig.bus.chips.items():
            if a != 0x0E:
                assert (chip.settings().osr, chip.settings().dig_filt) == (before.osr, before.dig_filt)
        assert len(rig.cycles(5)["wrench/sensor1"]) == 5  # and the daemon goes on
        rig.bus.faults.clear()
        rig.cycles(20)  # its reset, one step a cycle
        assert not d.reader.failing
        chip = rig.bus.chips[0x0E]
        assert (chip.settings().osr, chip.settings().dig_filt) == (before.osr, before.dig_filt)
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


def test_a_reload_whose_accuracy_chooses_another_conversion_writes_it_to_the_chips(tmp_path):
    from ftsensord.processing.pipeline import channel_sigma_t

    rig = Rig(tmp_path)
    try:
        d = rig.daemon
        tare(rig)
        before = d.config.settings
        path = d.config.path
        path.write_text(path.read_text().replace('name = "sensor1"', 'name = "sensor1"\naccuracy = "0.03N"'))
        expected = load_config(path)
        acc.apply_accuracy(expected)
        assert expected.settings != before  # the precondition: the key asks for another conversion
        reply = rig.request(cmd="reload")
        assert reply["ok"] and reply["result"]["tare"]["sensor1"].startswith("kept"), reply
        new = expected.settings
        assert d.config.settings == d.reader.settings == new
        assert {c.settings() for c in rig.bus.chips.values()} == {rig.bus.chips[0x0C].settings()}
        assert (rig.bus.chips[0x0C].settings().osr, rig.bus.chips[0x0C].settings().dig_filt) == (
            new.osr,
            new.dig_filt,
        )
        np.testing.assert_array_equal(d.sensors[0].sigma_t, channel_sigma_t(new, 8))
        assert len(rig.cycles(5)["wrench/sensor1"]) == 5 and not d.reader.failing
        # A chip that does not take the file's conversion: the reload refused, naming the file
        # and the chip, the running conversion kept on the others.
        path.write_text(path.read_text().replace('accuracy = "0.03N"', 'accuracy = "0.2N"'))
        rig.bus.faults.nack(0x0E)
        reply = rig.request(cmd="reload")
        assert not reply["ok"] and reply["error"].startswith(f"{path}: chip: OSR "), reply
        assert "MLX90393 at 0x0E" in reply["error"] and "nothing else changed" in reply["error"]
        assert d.config.settings == d.reader.settings == new and d.reader.failing == {0x0E}
        assert (rig.bus.chips[0x0C].settings().osr, rig.bus.chips[0x0C].settings().dig_filt) == (
            new.osr,
            new.dig_filt,
        )
        rig.bus.faults.clear()
        path.write_text(path.read_text().replace('accuracy = "0.2N"', 'accuracy = "0.03N"'))
        # The chips' other settings still need a restart.
        path.write_text(path.read_text().replace("[chip]\n", "[chip]\ngain_sel = 1\n"))
        reply = rig.request(cmd="reload")
        assert not reply["ok"] and "changing chip needs a restart" in reply["error"], reply
        assert d.config.settings == new
    finally:
        rig.close()


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


@pytest.mark.parametrize(
    "changed, said", [(True, "the chips' conversion changed to it"), (False, "as running")]
)
def test_set_accuracy_says_whether_the_chips_conversion_changed(monkeypatch, capsys, changed, said):
    import argparse
    from types import SimpleNamespace

    from ftsensord.cli import service

    result = {
        "rate_hz": 64.4,
        "averaging": 1,
        "effective_rate_hz": 64.4,
        "osr": 2,
        "dig_filt": 2,
        "conversion_changed": changed,
        "sigma": {"sensor1": [0.02, 0.03, 0.02, 0.003, 0.003, 0.003]},
    }
    monkeypatch.setattr(service, "control_client", lambda args: SimpleNamespace(set=lambda **kw: result))
    args = argparse.Namespace(
        accuracy=["0.03N"], rate=None, averaging=None, lowpass=None, estimator=None, sensor=None
    )
    assert service.cmd_set(args) == 0
    first = capsys.readouterr().out.splitlines()[0]
    assert (
        first
        == f"rate 64.4 Hz, averaging 1, low-pass off: 64.4 independent samples a second (OSR 2, DIG_FILT 2, {said})"
    )


def test_the_running_daemon_plans_an_accuracy_in_a_worker_and_applies_it_between_cycles(tmp_path):
    """`run`'s daemon (`Daemon.plans`): the request is answered once planned and applied; a
    second one meanwhile is refused at once; a tare between the request and the plan's end
    makes the plan stale: an error, nothing changed."""
    from ftsensord.daemon.plans import Plans

    rig = Rig(tmp_path)
    try:
        d = rig.daemon
        d.plans = Plans(d.control.reply)
        before = d.config.settings
        expected = running_plan(rig, "0.03N")
        assert expected.settings != before  # the precondition: a change to apply
        rig.req.send(json.dumps({"cmd": "set", "accuracy": "0.03N"}).encode())
        d.handle_control()
        assert not rig.req.poll(0) and d.config.settings == before  # not yet answered nor applied
        other = d.control.handle(json.dumps({"cmd": "set", "accuracy": "0.2N"}).encode(), [b"x"])
        assert other == {"ok": False, "error": "accuracy: another is being planned: wait for its reply"}
        d.plans.wait(60)
        rig.cycles(1)  # the loop runs while it plans
        d.plans.poll()  # between cycles, as `run` does
        assert rig.req.poll(1000)
        reply = json.loads(rig.req.recv())
        assert reply["ok"] and reply["result"]["conversion_changed"], reply
        assert d.config.settings == d.reader.settings == expected.settings
        # A tare while it plans: the plan, made for the untared sensors, is not applied.
        rig.req.send(json.dumps({"cmd": "set", "accuracy": "0.2N"}).encode())
        d.handle_control()
        tared = d.control.handle(json.dumps({"cmd": "tare", "samples": 10}).encode(), [b"y"])
        assert tared is None  # answered when done, to another client
        rig.cycles(10)
        assert all(p.tared for p in d.sensors)
        d.plans.wait(60)
        d.plans.poll()
        assert rig.req.poll(1000)
        reply = json.loads(rig.req.recv())
        assert not reply["ok"] and "changed while it was planned" in reply["error"], reply
        assert d.config.settings == expected.settings
        assert len(rig.cycles(3)["wrench/sensor1"]) == 3
    finally:
        rig.close()
