"""The cheap cycle: messages built once and reused, replies decoded as one block exactly as
one chip at a time, the board known at the daemon's start, and the CPU benchmark's quick
mode (its structure, never a timing threshold)."""

from __future__ import annotations

import json
import logging
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ftsensord.acquire.reader import Reader
from ftsensord.chip import mlx90393 as mlx
from ftsensord.chip.block import BlockDecoder
from ftsensord.chip.driver import MLX90393
from ftsensord.errors import ChipError
from ftsensord.sim import StaticScene, VirtualClock, simulated_bus

from .test_daemon import Rig

ROOT = Path(__file__).resolve().parent.parent
ADDRESSES = [0x0C, 0x0D, 0x0E, 0x0F]


def _scene() -> StaticScene:
    rng = np.random.default_rng(3)
    return StaticScene({a: rng.uniform(-2e-3, 2e-3, 3) for a in ADDRESSES}, dict.fromkeys(ADDRESSES, 30.0))


def _reader(adapter: str = "permissive") -> Reader:
    bus = simulated_bus(_scene(), clock=VirtualClock(), bus_hz=400e3, adapter=adapter, seed=1)
    reader = Reader(
        bus,
        [MLX90393(bus, a, sleep=bus.sleep) for a in ADDRESSES],
        "overlapped",
        mlx.Settings(),
        readback_every=0,
    )
    assert reader.start() == {}
    return reader


@pytest.mark.parametrize("adapter", ["permissive", "bcm2835", "designware"])
def test_messages_are_built_once_and_reused(adapter):
    reader = _reader(adapter)
    reader.read()
    plans = dict(reader.xfer._plans)
    firsts = [c.sm_messages()[0] for c in reader.chips]
    for _ in range(3):
        results = reader.read()
        assert all(r.ok for r in results.values())
    assert reader.xfer._plans.keys() == plans.keys()
    assert all(reader.xfer._plans[k] is plans[k] for k in plans)  # the same RM messages every cycle
    assert [c.sm_messages()[0] for c in reader.chips] == firsts and all(
        a is b for a, b in zip((c.sm_messages()[0] for c in reader.chips), firsts)
    )


def _one_by_one(chips: list[MLX90393], block: np.ndarray, zyxt: int) -> list:
    out = []
    for chip, row in zip(chips, block):
        try:
            out.append(chip.decode_measurement(bytes(row), zyxt))
        except ChipError as exc:
            out.append(exc)
    return out


@pytest.mark.parametrize("zyxt", [mlx.ZYXT_XYZ, mlx.ZYXT_XYZT, mlx.ZYXT_Y])
@pytest.mark.parametrize("res", [0, 3])
def test_block_decoding_equals_one_chip_at_a_time(zyxt, res):
    """Random words (rails and saturation included), bad status bytes among them: the block
    decoder gives what the per-chip decoder gives, errors included."""
    bus = simulated_bus(_scene(), clock=VirtualClock())
    chips = [MLX90393(bus, a, sleep=bus.sleep) for a in ADDRESSES]
    for c in chips:
        c.reset()
        c.configure(mlx.Settings(res_x=res, res_y=res, res_z=res))
    decoder = BlockDecoder(chips, zyxt)
    rng = np.random.default_rng(7)
    k = len(mlx.zyxt_items(zyxt))
    for _ in range(50):
        block = rng.integers(0, 256, (len(chips), 1 + 2 * k)).astype(np.uint8)
        block[:, 0] = k - 1  # D1:D0 right for these items ...
        block[1, 0] = rng.choice([0x10, 0x10 | (k - 1), (k % 4)])  # ... except: ERROR, or D1:D0 wrong
        block[2, 1:3] = rng.choice([[0x80, 0x00], [0x7F, 0xFF], [0xFF, 0xFF], [0, 0]])  # the rails
        slow = _one_by_one(chips, block, zyxt)
        rows = [int(i) for i in rng.permutation(len(chips))[: len(chips) - 3]]  # some read, in another order
        for fast, want in (
            (decoder.decode(block), slow),
            (decoder.decode(block, rows), [slow[i] for i in rows]),
        ):
            _assert_same(fast, want)


def _assert_same(fast: list, slow: list) -> None:
    assert len(fast) == len(slow)
    for f, s in zip(fast, slow):
        assert type(f) is type(s)
        if isinstance(s, ChipError):
            assert str(f) == str(s)
            continue
        np.testing.assert_array_equal(f.field_t, s.field_t)
        np.testing.assert_array_equal(f.saturated, s.saturated)
        assert f.any_saturated == s.any_saturated and f.raw == s.raw and f.status == s.status
        assert f.temperature_c == s.temperature_c


def test_block_decoder_is_rebuilt_after_a_reconfiguration():
    reader = _reader()
    reader.read()
    (plan,) = reader.xfer._plans.values()
    chip = reader.chips[0]
    chip.configure(mlx.Settings(gain_sel=5))  # a new scale: the old decoder would be wrong
    assert not plan.decoder.valid_for(reader.chips)
    results = reader.read()
    assert results[reader.chips[0].address].ok
    truth = _scene().field_t(chip.address, 0.0)
    # 50 uT: the chips' noise at these settings is a few uT, a wrong scale (x2.5) would be mT off.
    assert np.allclose(results[reader.chips[0].address].measurement.field_t, truth, atol=50e-6)


class BoardBus:
    """A simulated board behind the surface of `acquire.bus.LinuxI2CBus`: an adapter
    number (nothing in sysfs under it), no timing until `acquire.board` measures it."""

    def __init__(self, inner):
        self.inner, self.number, self.timing = inner, 977, None

    def i2c_rdwr(self, *msgs):
        self.inner.i2c_rdwr(*msgs)

    def sleep(self, s):
        self.inner.sleep(s)

    def monotonic(self):
        return self.inner.monotonic()

    def close(self):
        self.inner.close()


def test_daemon_knows_a_real_board_at_start(tmp_path, caplog):
    """On a real bus the daemon measures ioctl cost and clock, warns of a slow clock, and
    bounds the rate and reports with what it measured; on a simulated one it takes its timing."""
    rig = Rig(tmp_path)
    try:
        sim = rig.daemon.status()
        assert (
            sim["adapter"] == "bcm2835" and sim["clock_hz"] == 400e3 and sim["ioctl_us"] == pytest.approx(60)
        )
        slow = simulated_bus(rig.scene, clock=rig.clock, bus_hz=400e3, clock_hz=250e3, ioctl_s=80e-6, seed=5)
        rig.daemon.__init__(rig.config, BoardBus(slow), rig.pub, rig.router, clock=rig.clock.now)
        assert rig.daemon.status()["ioctl_us"] is None  # not measured before start
        with caplog.at_level(logging.WARNING, logger="ftsensord"):
            rig.daemon.start()
        assert any(
            "measures 250 kHz" in r.getMessage() and "core_freq" in r.getMessage() for r in caplog.records
        )
        status = rig.daemon.status()
        assert status["clock_hz"] == pytest.approx(250e3, rel=0.02)
        assert status["ioctl_us"] == pytest.approx(80, abs=5)
        assert status["bound_hz"] == pytest.approx(rig.config.bound(rig.daemon.board_timing).rate_hz)
        assert status["bound_hz"] < sim["bound_hz"]  # the slower board's bound, not the configured one
        assert rig.daemon.reader.bus_hz == pytest.approx(250e3, rel=0.02)
    finally:
        rig.close()


def test_cycle_cpu_quick_mode_reports_the_ratio():
    out = subprocess.run(
        [sys.executable, "-m", "benchmarks.performance.cycle_cpu", "--quick", "--json"],
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
        cwd=ROOT,
    ).stdout
    r = json.loads(out)
    for key in (
        "reference_us",
        "daemon_linear_us",
        "bus_us",
        "daemon_own_us",
        "daemon_nonlinear_us",
        "nonlinear_per_sensor_us",
        "estimate_per_sensor_us",
        "pi_factor",
        "pi_estimate_linear_us",
        "pinned_cpu",
        "load_1min",
    ):
        assert np.isfinite(r[key]), key
    assert r["reference_us"] > 0 and r["daemon_linear_us"] > 0
    # The stand-in bus is measured apart and taken out of the daemon's side only: the
    # reference has no bus, so the ratio is of the daemon's own work.
    assert 0 < r["bus_us"] < r["daemon_linear_us"]
    s = r["samples"]
    own = sorted(d - b for d, b in zip(s["linear"], s["bus"]))
    assert r["daemon_own_us"] == pytest.approx(own[len(own) // 2])  # an odd count of rounds: the middle one
    assert r["ratio"] == pytest.approx(r["daemon_own_us"] / r["reference_us"])
    paired = sorted((d - b) / ref for d, b, ref in zip(s["linear"], s["bus"], s["reference"]))
    assert r["ratio_paired"] == pytest.approx(paired[len(paired) // 2])
    assert r["pi_estimate_linear_us"] == pytest.approx(r["daemon_own_us"] * r["pi_factor"])
    assert len(s["linear"]) == r["rounds"] == len(s["reference"]) == len(s["bus"])
    assert r["failing_chips"] == 0  # the instant bus must keep every chip healthy, or the figure lies
    assert r["inconsistent_samples"] == 0  # and agreeing: the cycle measured is the usual one


@pytest.mark.parametrize("adapter", ["permissive", "bcm2835"])
def test_one_plan_reads_every_order_and_every_subset(adapter):
    """The chip read back is read last (each chip in turn gives its own RM order) and faults
    leave chips out: one plan serves them all (no plan built between two transfers, no
    memory grown by faults), and each chip's reply still lands in its own result."""
    addresses = list(range(0x0C, 0x1C))
    rng = np.random.default_rng(5)
    scene = StaticScene({a: rng.uniform(-2e-3, 2e-3, 3) for a in addresses}, dict.fromkeys(addresses, 30.0))
    bus = simulated_bus(scene, clock=VirtualClock(), bus_hz=400e3, adapter=adapter, seed=1)
    reader = Reader(
        bus,
        [MLX90393(bus, a, sleep=bus.sleep) for a in addresses],
        "overlapped",
        mlx.Settings(),
        readback_every=1,
    )
    assert reader.start() == {}
    assert all(r.ok for r in reader.read().values())
    (plan,) = reader.xfer._plans.values()
    for _ in range(2 * len(addresses)):
        assert all(r.ok for r in reader.read().values())
    for _ in range(20):
        chips = [reader.chips[i] for i in rng.permutation(len(addresses))[: rng.integers(1, len(addresses))]]
        for c in chips:
            c.start_single(mlx.ZYXT_XYZ)
        bus.sleep(reader.conversion_s(mlx.ZYXT_XYZ))
        results = reader.xfer.results(reader.xfer.read_block(chips, mlx.ZYXT_XYZ))
        assert sorted(results) == sorted(c.address for c in chips)
        for a, r in results.items():
            # 50 uT: the noise is a few uT; another chip's reply is mT away (fields drawn over +-2 mT).
            assert r.ok and np.allclose(r.measurement.field_t, scene.field_t(a, 0.0), atol=50e-6)
    assert list(reader.xfer._plans.values()) == [plan]


def test_nonlinear_cpu_quick_mode_reports_moving_and_rest():
    out = subprocess.run(
        [sys.executable, "-m", "benchmarks.performance.nonlinear_cpu", "--quick", "--json"],
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
        cwd=ROOT,
    ).stdout
    r = json.loads(out)
    assert r["samples"] == round(2 * 100 / 1.3) and r["fraction"] == 0.4 and r["hz"] == 1.3
    for name in ("moving", "rest"):
        s = r[name]["cpu_us"]
        assert 0 < s["p50"] <= s["p99"] <= s["max"] and np.isfinite(s["mean"]), name
        assert r[name]["not_converged"] == 0 and r[name]["iterations_per_sample"] >= 1
    # The moving load is followed: the estimates stay near it (the noise's and the model's
    # error, about 0.05 N and 6 mNm here, not a load's worth: 20 N, 0.08 Nm).
    assert np.all(np.array(r["moving"]["rms_error"]) < [0.5, 0.5, 0.5, 0.02, 0.02, 0.02])


def test_board_mode_adds_bus_and_scaled_cpu_per_configuration(tmp_path):
    from ftsensord.acquire.bound import cycle_bound

    path = tmp_path / "board.json"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "benchmarks.performance.board",
            "--quick",
            "--pi-factor",
            "5",
            "--out",
            str(path),
        ],
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
        cwd=ROOT,
    )
    r = json.loads(path.read_text())
    assert r["facts"]["python"] and r["pi_factor"] == 5 and "doctor" not in r
    own = r["cycle_cpu"]["daemon_own_us"]
    p99 = {k: r["nonlinear"][k]["cpu_us"]["p99"] for k in ("moving", "rest")}
    extra = {
        "linear (default)": 0.0,
        "nonlinear, one sensor, load moving": p99["moving"],
        "nonlinear, both sensors, at rest": 2 * p99["rest"],
        "nonlinear, both sensors, load moving": 2 * p99["moving"],
    }
    rows = r["table"]
    assert len(rows) == 3 * 3 * 4  # boards x bus levers x configurations
    for row in rows:
        assert row["cpu_ms"] == pytest.approx((own + extra[row["configuration"]]) * 5 * 1e-3)
        assert row["cycle_ms"] == pytest.approx(row["bus_ms"] + row["cpu_ms"])
        assert row["holds"] == (row["cycle_ms"] <= 8.0)  # 20 % of a 10 ms period spare
    pessimistic = [
        x for x in rows if x["board"].startswith("pessimistic") and not x["readback"] and not x["temperature"]
    ]
    bound = cycle_bound(
        "burst", 16, mlx.Settings(), 250e3, 150e-6, readback=False, temperature=False, adapter="bcm2835"
    )
    assert pessimistic[0]["bus_ms"] == pytest.approx(bound.cycle_s * 1e3)
