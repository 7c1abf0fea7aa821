"""The boundary never lets an exception out: requests and files that used to kill the
daemon (Python's 4300-digit int limit, deep nesting) become error replies or refused
reloads; the loop's care follows a reload; a NACK on read-back is not register drift."""

from __future__ import annotations

import json
import logging
import shutil
import threading
import time

import numpy as np
import pytest
import zmq

from ftsensord.calibration.calfile import MAX_CALIBRATION_BYTES, Calibration
from ftsensord.config.file import builtin_path
from ftsensord.daemon.control import Budget, Control
from ftsensord.daemon.sdnotify import Notifier
from ftsensord.docfile import MAX_DEPTH, load_toml, parse_json
from ftsensord.errors import ConfigError
from ftsensord.protocol import wire
from ftsensord.sim import load_scene

from .conftest import assert_names_file_and_key
from .test_daemon import Rig


@pytest.fixture
def make_rig(tmp_path):
    """``Rig(tmp_path, ...)``, closed at teardown whether the test passed or not."""
    made: list[Rig] = []

    def make(**kwargs) -> Rig:
        made.append(Rig(tmp_path, **kwargs))
        return made[-1]

    yield make
    for rig in made:
        rig.close()


HUGE = "1" * 5000  # over Python's 4300-digit int-from-string limit: a plain ValueError


@pytest.mark.parametrize(
    "raw",
    [
        '{"cmd":"status","n":' + HUGE + "}",  # killed the daemon: exit 1
        '{"cmd":"set","rate_hz":' + HUGE + "}",
        '{"cmd":"tare","samples":-' + HUGE + "}",
        '{"cmd":"status","x":' + "[" * 5000 + "]" * 5000 + "}",
        "[" * 5000 + "]" * 5000,
        '{"cmd":"status","x":' + '{"a":' * 9 + "1" + "}" * 9 + "}",  # over the request depth
    ],
)
def test_requests_that_used_to_kill_are_answered_with_an_error_and_the_loop_goes_on(make_rig, raw):
    rig = make_rig()
    rig.cycles(3)
    rig.req.send(raw.encode())
    rig.daemon.handle_control()
    assert rig.req.poll(1000)
    reply = json.loads(rig.req.recv())
    assert reply["ok"] is False and "limits" in reply["error"]
    out = rig.cycles(3)
    assert [s.seq for s in out["wrench/sensor1"]] == [3, 4, 5]
    assert rig.request(cmd="status")["result"]["cycles"] == 6


def test_parse_json_names_the_key_of_what_is_over_the_limits():
    with pytest.raises(ConfigError, match=r"^n: an integer of 5000 characters"):
        parse_json('{"cmd":"status","n":' + HUGE + "}")
    with pytest.raises(ConfigError, match=r"^a\[1\]\.b: nested deeper than 3"):
        parse_json('{"a":[1,{"b":[[1]]}]}', max_depth=3)  # object, array, object: 3 levels; [[ goes over
    with pytest.raises(ConfigError, match="more than the 10 accepted"):
        parse_json(b" " * 11, max_bytes=10)
    assert parse_json('{"a":[1,{"b":[1.5e3]}]}', max_depth=4) == {"a": [1, {"b": [1500.0]}]}


def calibration_with(tmp_path, key: str, literal: str):
    doc = json.loads(builtin_path("sim-sensor1.json").read_text())
    doc[key] = "PLACEHOLDER"
    path = tmp_path / "cal.json"
    path.write_text(json.dumps(doc, indent=1).replace('"PLACEHOLDER"', literal))
    return path


@pytest.mark.parametrize(
    ("key", "literal", "expected"),
    [
        ("version", HUGE, "an integer of 5000 characters"),
        ("wrench_range", "[" * (MAX_DEPTH + 2) + "]" * (MAX_DEPTH + 2), f"nested deeper than {MAX_DEPTH}"),
        # Python's parser gives up (RecursionError) before saying where: the file is named, not the key.
        ("", "[" * 5000 + "]" * 5000, "nested deeper than"),
    ],
)
def test_a_calibration_file_over_the_limits_is_refused_naming_file_and_key(tmp_path, key, literal, expected):
    path = calibration_with(tmp_path, key or "wrench_range", literal)
    assert_names_file_and_key(Calibration.load, path, key, expected)


def test_a_sighup_with_such_a_calibration_is_a_refused_reload_not_an_exit(tmp_path, make_rig):
    cal = tmp_path / "sensor1.json"
    shutil.copy(builtin_path("sim-sensor1.json"), cal)
    rig = make_rig(sensor1_cal=str(cal))
    rig.cycles(2)
    text = cal.read_text()
    cal.write_text(text.replace('"version": 1', '"version": ' + HUGE, 1))
    reply = rig.request(cmd="reload")
    assert reply["ok"] is False and str(cal) in reply["error"] and "version" in reply["error"]
    cal.write_text("[" * 5000 + "]" * 5000)
    rig.daemon.reload_requested = True  # what SIGHUP does; run() reloads between cycles
    with pytest.raises(ConfigError, match=str(cal)):
        rig.daemon.reload()
    assert [s.seq for s in rig.cycles(2)["wrench/sensor1"]] == [2, 3]  # the running calibration stays


def test_a_huge_calibration_file_is_refused_by_its_size_naming_file_limit_and_size(tmp_path):
    """A 200 MB calibration file (the issue's, which stalled the loop 7.75 s on SIGHUP) is
    refused by its size before it is read, the reload refused, the running calibration kept."""
    cal = tmp_path / "sensor1.json"
    shutil.copy(builtin_path("sim-sensor1.json"), cal)
    rig = Rig(tmp_path, sensor1_cal=str(cal))
    rig.cycles(2)
    with cal.open("r+b") as f:
        f.truncate(200 * 2**20)  # sparse: no disk written, and the same size to stat()
    reply = rig.request(cmd="reload")
    assert not reply["ok"]
    assert str(cal) in reply["error"] and f"{200 * 2**20} bytes" in reply["error"], reply
    assert f"{MAX_CALIBRATION_BYTES} bytes a calibration file may hold" in reply["error"], reply
    assert [s.seq for s in rig.cycles(2)["wrench/sensor1"]] == [2, 3]  # the running calibration stays
    rig.close()


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("version = 1\n[chip]\nosr = " + HUGE + "\n", "line 3, key chip.osr"),
        ("version = 1\nx = " + "[" * 5000 + "]" * 5000 + "\n", "nested deeper than"),
        ("version = 1\nx = " + "[" * 40 + "]" * 40 + "\n", "x[0]"),
        ("version = 1\nrate_hz = 1" + "0" * 150 + "\n", "rate_hz: an integer of more than"),
    ],
)
def test_a_toml_file_over_the_limits_is_refused_naming_file_and_key(tmp_path, text, expected):
    path = tmp_path / "c.toml"
    path.write_text(text)
    assert_names_file_and_key(load_toml, path, "", expected)


def test_reload_applies_stuck_cycles_and_readback_every(tmp_path, make_rig):
    rig = make_rig()
    assert rig.daemon.reader.readback_every == 1
    (tmp_path / "ftsensord.toml").write_text(
        (tmp_path / "ftsensord.toml")
        .read_text()
        .replace("rate_hz = 100", "rate_hz = 100\nstuck_cycles = 0\nreadback_every = 5")
    )
    assert rig.request(cmd="reload")["ok"]
    assert rig.daemon.reader.readback_every == 5
    assert rig.daemon.reader.care.stuck_cycles == 0
    transfers = rig.bus.transfers
    rig.cycles(10)
    per_cycle_5 = (rig.bus.transfers - transfers) / 10
    (tmp_path / "ftsensord.toml").write_text(
        (tmp_path / "ftsensord.toml").read_text().replace("readback_every = 5", "readback_every = 1")
    )
    assert rig.request(cmd="reload")["ok"]
    transfers = rig.bus.transfers
    rig.cycles(10)
    assert (rig.bus.transfers - transfers) / 10 > per_cycle_5  # read back every cycle: more transfers


def test_a_rate_too_slow_for_the_watchdog_is_refused(tmp_path, make_rig):
    notifier = Notifier(environ={"NOTIFY_SOCKET": str(tmp_path / "none"), "WATCHDOG_USEC": "5000000"})
    rig = make_rig(notifier=notifier)
    reply = rig.request(cmd="set", rate_hz=0.1)  # 10 s between cycles: 10 s between pings
    assert reply["ok"] is False and "WatchdogSec=5" in reply["error"]
    assert rig.daemon.config.rate_hz == 100
    assert rig.request(cmd="set", rate_hz=0.5)["ok"]  # a cycle every 2 s: two per WatchdogSec
    with pytest.raises(ConfigError, match="too slow for the watchdog"):
        Notifier(environ={"WATCHDOG_USEC": "1000000"}).check_rate(1.0)
    Notifier(environ={}).check_rate(0.1)  # no watchdog: any rate


def test_status_is_built_once_per_cycle_and_after_any_change(make_rig):
    rig = make_rig()
    rig.cycles(2)
    first = rig.request(cmd="status")["result"]
    again = rig.request(cmd="status")["result"]
    assert again == first  # the same cycle: the cached reply
    assert rig.request(cmd="set", averaging=4)["ok"]
    assert rig.request(cmd="status")["result"]["averaging"] == 4  # a change shows at once
    rig.cycles(1)
    assert rig.request(cmd="status")["result"]["cycles"] == 3


def test_requests_are_served_in_turn_one_per_client_within_the_budget(make_rig):
    rig = make_rig()
    ctx = zmq.Context.instance()
    router = ctx.socket(zmq.ROUTER)
    router.bind("inproc://fair")
    control = Control(router, rig.daemon)
    greedy, modest = ctx.socket(zmq.DEALER), ctx.socket(zmq.DEALER)
    for sock, n in ((greedy, 12), (modest, 3)):
        sock.connect("inproc://fair")
        for i in range(n):
            sock.send_multipart([b"", json.dumps({"cmd": "status", "i": i}).encode()])
    spent = control.serve_waiting(Budget(requests=6))
    assert spent
    got = {"greedy": 0, "modest": 0}
    for name, sock in (("greedy", greedy), ("modest", modest)):
        while sock.poll(50):
            sock.recv_multipart()
            got[name] += 1
    assert got == {"greedy": 3, "modest": 3}  # one each per turn, however many the greedy one sent
    assert control.held == 9  # the rest waits for the next cycle
    assert not control.serve_waiting(Budget(requests=100)) and control.held == 0
    for sock in (greedy, modest, router):
        sock.close(linger=0)


def test_a_nack_during_read_back_is_not_register_drift(make_rig, caplog):
    rig = make_rig()
    rng = np.random.default_rng(3)
    rig.bus.faults.take_nack = lambda address: bool(rng.random() < 0.05)  # 5 % of transfers NACKed
    with caplog.at_level(logging.INFO, logger="ftsensord"):
        rig.cycles(1000)
    health = rig.daemon.reader.health.values()
    assert sum(h.register_drifts for h in health) == 0 and sum(h.reinits for h in health) == 0
    read_back_nacks = [r for r in caplog.records if "no answer to the register read-back" in r.getMessage()]
    assert len(read_back_nacks) > 10  # the case that counted as drift and forced a reset before


def test_a_chip_failing_and_returning_is_logged_once_per_transition(make_rig, caplog):
    from .test_faults import fault

    rig = make_rig(scene_extra=fault("nack", 0.3, 0.6, address=0x0E))
    with caplog.at_level(logging.INFO, logger="ftsensord"):
        rig.cycles(200)
    about = [r.getMessage() for r in caplog.records if "0x0E" in r.getMessage()]
    assert len([m for m in about if "failing" in m]) == 1, about
    assert len([m for m in about if " back" in m]) == 1, about


def test_a_reload_reads_its_files_off_the_loop_and_a_flood_is_one_reload(tmp_path, monkeypatch):
    """The daemon as `ftsensord run` makes it (reloads in a worker thread): while a reload's
    file work is held up (a slow disk, a big file), the loop goes on publishing every
    cycle; the 50 requests that came meanwhile are answered by one reload after it, and
    the replies all say ok."""
    from ftsensord.config.file import load_config
    from ftsensord.daemon import daemon as daemon_module

    from .conftest import InProcess
    from .test_daemon import write_config

    release, reading = threading.Event(), threading.Event()
    real = daemon_module.reload_config

    def slow_reload_config(*args, **kwargs):
        reading.set()
        assert release.wait(30)  # held until the test has run its cycles
        return real(*args, **kwargs)

    monkeypatch.setattr(daemon_module, "reload_config", slow_reload_config)
    rig = InProcess(
        load_config(write_config(tmp_path)),
        load_scene(tmp_path / "scene.toml"),
        subscribe=b"wrench/sensor1\0",
        background_reload=True,
    )
    d = rig.daemon
    dealer = zmq.Context.instance().socket(zmq.DEALER)
    dealer.connect(rig.router.getsockopt(zmq.LAST_ENDPOINT).decode())

    def cycles(n: int) -> list[int]:
        seqs = []
        for _ in range(n):
            deadline = rig.clock.now() + d.period_s
            d.cycle()
            d.handle_control()
            d.reloads.poll()
            rig.clock.wait_until(deadline)
            while rig.sub.poll(0):
                seqs.append(wire.decode(rig.sub.recv()).seq)
        return seqs

    dealer.send_multipart([b"", b'{"cmd": "reload"}'])
    cycles(2)
    assert reading.wait(10)  # the worker is in the file work, held
    for _ in range(50):
        dealer.send_multipart([b"", b'{"cmd": "reload"}'])
    seqs = cycles(100)  # 1 s of the loop while the first reload's files are read
    assert seqs == list(range(2, 102)) and not dealer.poll(0)  # every cycle published, no reply yet
    release.set()
    replies = []
    # The worker finishes; the loop swaps it in and answers. The second reload may start
    # only RELOAD_EVERY_S of real time after the first: wait in real time, not in cycles
    # (a fast host ran 500 cycles in less).
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline:
        cycles(1)
        d.reloads.wait(0.01)
        while dealer.poll(0):
            replies.append(json.loads(dealer.recv_multipart()[-1]))
        if len(replies) == 51:
            break
    assert len(replies) == 51 and all(r["ok"] for r in replies), replies[:3]
    assert d.reloads.done == 2  # the first, and one for the 50 that came during it
    dealer.close(linger=0)
    rig.close()
