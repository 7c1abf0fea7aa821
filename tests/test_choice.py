"""The daemon chooses the scheduler and read-back a configuration leaves unnamed (issue 26):
the one that holds the rate with the most margin, keeping the read-back while some option
holds with the target's spare; every lever named with its bound when nothing holds."""

from __future__ import annotations

import logging

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ftsensord.acquire import choice
from ftsensord.acquire.bound import SCHEDULERS, cycle_bound
from ftsensord.chip import mlx90393 as mlx
from ftsensord.chip.i2c import BusTiming
from ftsensord.config.file import load_config, reload_config
from ftsensord.daemon.daemon import Daemon
from ftsensord.errors import ConfigError
from ftsensord.sim import VirtualClock, load_scene, simulated_bus
from ftsensord.sim.bus import SimulatedBus

from .test_daemon import write_config

#: The issue's pessimistic board: a slow ioctl and the I2C clock fallen to 250 kHz with the core clock.
PESSIMISTIC = "sim?adapter=bcm2835&ioctl_us=150&clock_hz=250000"
#: A Raspberry Pi 4 (the simulator's defaults: bcm2835, 60 us an ioctl, 400 kHz).
PI4 = choice.Bus(16, mlx.Settings(), 400e3, 60e-6, "bcm2835", temperature=True)
#: What moves the bound of burst without the read-back there (a shorter conversion does not: burst waits for none).
LEVER_NAMES = ("the scheduler", "temperature_every = 0", "the bus clock at 400 kHz", "a lower rate")


def _with_bus(tmp_path, bus: str, extra: str = "", rate_hz: float = 100):
    path = write_config(tmp_path, extra, rate_hz=rate_hz)
    path.write_text(path.read_text().replace('bus = "sim:scene.toml"', f'bus = "sim:scene.toml?{bus[4:]}"'))
    return path


def test_a_pi4_at_100_hz_gets_burst_with_the_read_back_every_cycle(tmp_path):
    config = load_config(write_config(tmp_path))
    assert (config.scheduler, config.readback_every) == ("burst", 1)
    assert "36% of the period spare" in config.choice and "chosen: readback_every, scheduler" in config.choice


def test_the_pessimistic_board_drops_the_read_back_and_names_every_lever(tmp_path):
    # burst with the read-back: 88 Hz (every 100 cycles, the slowest cycle counted); without: 105.2 Hz
    config = load_config(_with_bus(tmp_path, PESSIMISTIC))
    assert (config.scheduler, config.readback_every) == ("burst", 0)
    assert "bound 105.2 Hz, 5% of the period spare" in config.choice
    for lever in LEVER_NAMES:  # 5 % is under the 20 % target: what to move is said
        assert lever in config.choice, lever
    assert "the bus clock at 400 kHz, now 250 kHz (burst 146.2 Hz)" in config.choice, config.choice
    assert "readback_every = 0" not in config.choice and "OSR" not in config.choice  # nothing to gain there


def test_nothing_holds_names_every_lever_with_its_bound(tmp_path):
    with pytest.raises(ConfigError) as exc:
        load_config(_with_bus(tmp_path, PESSIMISTIC, rate_hz=130))
    msg = str(exc.value)
    assert "rate_hz: 130 Hz cannot be met" in msg and "burst: 105.2 Hz at most" in msg  # the fastest option
    for lever in LEVER_NAMES:
        assert lever in msg, lever
    assert "(without the read-back: naive 12.4, overlapped 69.4, burst 105.2 Hz)" in msg  # each scheduler
    assert "a lower rate (at most 84.1 Hz for 20% spare, 105.2 Hz at the bound; now 130 Hz)" in msg


def test_a_named_lever_is_kept(tmp_path):
    named = load_config(_with_bus(tmp_path, PESSIMISTIC, 'scheduler = "overlapped"', rate_hz=50))
    assert named.scheduler == "overlapped" and named.readback_every == 1  # 64 Hz holds 50 with 22 % spare
    assert "readback_every not in the file" in named.choice
    with pytest.raises(ConfigError, match="readback_every = 0"):  # burst with the read-back: 88 Hz
        load_config(_with_bus(tmp_path, PESSIMISTIC, "readback_every = 1", rate_hz=100))
    both = load_config(_with_bus(tmp_path, PESSIMISTIC, 'scheduler = "burst"\nreadback_every = 0'))
    assert both.choice.endswith("(as configured)")


def _oracle(bus: choice.Bus, rate_hz: float) -> list[tuple[str, bool, float]]:
    """Every option's spare, from `cycle_bound` directly."""
    return [
        (
            s,
            r,
            1
            - rate_hz
            * cycle_bound(
                s,
                bus.n_chips,
                bus.settings,
                bus.clock_hz,
                bus.ioctl_s,
                readback=r,
                temperature=bus.temperature,
                adapter=bus.adapter,
            ).cycle_s,
        )
        for s in SCHEDULERS
        for r in (True, False)
    ]


@settings(max_examples=150, deadline=None)
@given(
    clock=st.floats(100e3, 400e3),
    ioctl=st.floats(0, 300e-6),
    adapter=st.sampled_from(["permissive", "bcm2835", "designware", None]),
    n=st.integers(1, 16),
    rate=st.floats(5, 400),
    temperature=st.booleans(),
)
def test_the_choice_holds_the_rate_with_the_most_margin(clock, ioctl, adapter, n, rate, temperature):
    bus = choice.Bus(n, mlx.Settings(), clock, ioctl, adapter, temperature)
    options = _oracle(bus, rate)
    holding = [o for o in options if o[2] >= 0]
    if not holding:
        with pytest.raises(ConfigError, match="Levers: the scheduler"):
            choice.choose(bus, rate)
        return
    picked = choice.choose(bus, rate)
    spare = picked.spare(rate)
    assert spare >= 0
    checked = [o for o in holding if o[1] and o[2] >= choice.TARGET_SPARE]
    if checked:  # the read-back is kept whenever some scheduler holds with it and the target's spare
        assert picked.readback_every > 0 and spare == pytest.approx(max(o[2] for o in checked))
    else:  # else the most spare of all
        assert spare == pytest.approx(max(o[2] for o in holding))


def test_the_daemon_chooses_again_from_the_bus_measured_at_start(tmp_path, caplog):
    # The file says a Pi 4 (burst, read-back every cycle); the board measures 150 us ioctls at 250 kHz.
    config = load_config(write_config(tmp_path))
    assert (config.scheduler, config.readback_every) == ("burst", 1)
    clock = VirtualClock()
    bus = simulated_bus(
        load_scene(tmp_path / "scene.toml"),
        clock=clock,
        bus_hz=400e3,
        adapter="bcm2835",
        ioctl_s=150e-6,
        clock_hz=250e3,
    )
    bus.__class__ = _AdapterLike  # the daemon measures it at start (sysfs: none, rules unknown)
    daemon = Daemon(config, bus, _Null(), clock=clock.now)
    with caplog.at_level(logging.INFO, logger="ftsensord"):
        daemon.start()
    measured = daemon.board_timing
    assert measured is not None and measured.ioctl_s == pytest.approx(150e-6, rel=0.1)
    expected = choice.choose(config.bus_levers(measured), 100.0)
    assert (daemon.config.scheduler, daemon.config.readback_every) == (
        expected.scheduler,
        expected.readback_every,
    )
    assert expected.readback_every == 0  # the measured board needs it dropped
    assert (daemon.reader.scheduler, daemon.reader.readback_every) == (expected.scheduler, 0)
    assert any(
        r.levelno == logging.WARNING and "schedule: burst, no register read-back" in r.getMessage()
        for r in caplog.records
    )  # under the 20 % target: said loudly, with the levers
    assert daemon.status()["schedule"] == daemon.config.choice
    # A reload keeps the running scheduler (a restart chooses again) and chooses the read-back again.
    reloaded = reload_config(daemon.config, timing=measured)
    assert (reloaded.scheduler, reloaded.readback_every) == (expected.scheduler, 0)


class _AdapterLike(SimulatedBus):
    """The simulated board as a real adapter shows itself: a number, timing known once measured."""

    number = 99
    timing: BusTiming | None = None


class _Null:
    """A publisher that drops everything (the test reads the daemon's state, not its stream)."""

    def send(self, *args, **kwargs) -> None:
        pass
