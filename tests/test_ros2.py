"""The streams on the ROS 2 graph: `ftsensord run` with a ``[ros2]`` table starts the bridge,
and a separate process (tests/ros2_peer.py: Cyclone DDS with types written from ROS 2's
message files, nothing imported from ftsensord) reads and writes as a ROS 2 node would.

Isolation: every test module uses its own DDS domain (from the pid) and a CYCLONEDDS_URI
that keeps discovery on the loopback interface, multicast off, the peers found by unicast
on 127.0.0.1: parallel runs on one host do not see each other, nothing leaves the host.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("cyclonedds")  # the ros2 extra, which the test extra includes

from ftsensord.client import ControlClient  # noqa: E402
from ftsensord.config.file import load_config  # noqa: E402
from ftsensord.protocol import wire  # noqa: E402

from .conftest import StreamRecorder, assert_names_file_and_key, start_daemon  # noqa: E402
from .test_daemon import Rig, write_config  # noqa: E402

PEER = Path(__file__).with_name("ros2_peer.py")
DOMAIN = 100 + os.getpid() % 100  # 100-199: clear of ROS's default 0 and of other runs' domains
NS = "fts_test"
URI = (
    "<CycloneDDS><Domain Id='any'><General><Interfaces><NetworkInterface address='127.0.0.1'/></Interfaces>"
    "<AllowMulticast>false</AllowMulticast></General><Discovery><ParticipantIndex>auto</ParticipantIndex>"
    "<MaxAutoParticipantIndex>30</MaxAutoParticipantIndex><Peers><Peer address='127.0.0.1'/></Peers>"
    "</Discovery></Domain></CycloneDDS>"
)
ENV = {**os.environ, "CYCLONEDDS_URI": URI}
STREAMS = ["wrench/sensor1", "wrench/tip", "wrench/tip/compensated"]
GRAVITY = """
[gravity]
orientation = "stream"
stale_after_s = 0.5
[gravity.sensor1]
mass_kg = 0.05
com_m = [0.0, 0.0, 0.01]
[gravity.tip]
mass_kg = 0.05
com_m = [0.0, 0.0, 0.01]
"""
RAW = {
    "WrenchStamped": "geometry_msgs/msg/WrenchStamped",
    "DiagnosticArray": "diagnostic_msgs/msg/DiagnosticArray",
}


def rosbags_hash(name: str) -> str:
    """The RIHS01 hash of a ROS 2 Jazzy message by rosbags' own implementation (from .msg files)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY).hash_rihs01(name)


def peer(*steps: dict, timeout_s: float = 60) -> list[dict]:
    """Run the ROS 2 peer with ``steps``; its JSON lines."""
    done = subprocess.run(
        [sys.executable, str(PEER), str(DOMAIN), json.dumps(list(steps))],
        env=ENV,
        capture_output=True,
        text=True,
        timeout=timeout_s,
    )
    assert done.returncode == 0, done.stderr
    return [json.loads(line) for line in done.stdout.splitlines()]


def Reference(endpoint: str) -> StreamRecorder:  # noqa: N802 (a class's name to its callers)
    """Every sample of the streams, by (topic, stamp in ns), as the Python client receives them."""
    return StreamRecorder(endpoint, STREAMS, lambda s: (s.topic, round(s.t_wall * 1e9)))


@pytest.fixture(scope="module", params=["bridge", "in-loop"])
def daemon(tmp_path_factory, request) -> Iterator[tuple[Path, StreamRecorder]]:
    """A daemon with ``[ros2]``, each output in turn: the bridge process, the loop's own writes."""
    folder = tmp_path_factory.mktemp("ros2")
    config = write_config(
        folder,
        extra=f'[ros2]\nnamespace = "{NS}"\ndomain_id = {DOMAIN}\noutput = "{request.param}"\n' + GRAVITY,
    )
    proc, notify = start_daemon(
        config, folder, env={"CYCLONEDDS_URI": URI}, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    ref = Reference(f"ipc://{folder / 'ftsensord' / 'wrench'}")
    ref.start()
    try:
        yield folder / "ftsensord", ref
    finally:
        ref.stop.set()
        proc.terminate()
        proc.wait(timeout=20)
        notify.close()


def test_the_type_hashes_are_those_an_independent_implementation_computes():
    from ftsensord.ros2 import msgs

    for cls in (
        msgs.WrenchStamped,
        msgs.DiagnosticArray,
        msgs.QuaternionStamped,
        msgs.Imu,
        msgs.Empty,
        msgs.ParticipantEntitiesInfo,
    ):  # its Gid's char[16] and string<=256: FieldType ids of their own
        name = cls.__idl_typename__.replace("::dds_::", "::").rstrip("_").replace("::", "/")
        assert msgs.type_hash(cls) == rosbags_hash(name), name


@pytest.mark.parametrize("reliable", [True, False], ids=["default-qos", "sensor-data-qos"])
def test_a_ros2_subscriber_reads_every_wrench_as_the_zeromq_stream_has_it(daemon, reliable):
    folder, ref = daemon
    control = ControlClient(f"ipc://{folder / 'control'}")
    frames = control.status()["frames"]
    topics = {
        **{f"rt/{NS}/{s}": "WrenchStamped" for s in STREAMS},
        **{f"rt/{NS}/{s}/sigma": "WrenchStamped" for s in STREAMS},  # each wrench's sigma
        f"rt/{NS}/wrench/tip/status": "SampleStatus",
    }
    lines = peer({"do": "read", "topics": topics, "count": 30, "reliable": reliable})
    outputs = control.status()["outputs"]  # in-loop: what it wrote, for an operator
    if outputs:
        (out,) = outputs
        assert out["output"] == "in-loop" and out["write_errors"] == out["failures"] == 0
        # (the peer has gone: its readers may already be forgotten, 0.2 s after it left)
        assert out["namespace"] == NS and set(out["streams_read"]) <= set(STREAMS)
    time.sleep(0.1)  # the reference's last samples in
    (status,) = [line for line in lines if line["topic"].endswith("/status")]
    assert status["writer"]["type_name"] == "ftsensord_msgs::msg::dds_::SampleStatus_"
    for m in status["messages"]:
        stamp = m["header"]["stamp"]
        sample = ref.samples[("wrench/tip", stamp["sec"] * 10**9 + stamp["nanosec"])]
        assert (m["seq"], m["flags"], m["header"]["frame_id"]) == (
            sample.seq,
            sample.flags,
            frames["wrench/tip"],
        )
    seqs = [m["seq"] for m in status["messages"]]
    # missed: seqs the bridge did not get; a best-effort reader may also lose some on DDS
    gaps = [(m["missed"], b - a - 1) for a, b, m in zip(seqs, seqs[1:], status["messages"][1:])]
    assert all(missed == gap if reliable else missed <= gap for missed, gap in gaps), gaps
    for line in lines:
        if line is status:
            continue
        stream = line["topic"].removeprefix(f"rt/{NS}/")
        sigma = stream.endswith("/sigma")  # the sample's sigma: stamped and framed as its wrench
        stream = stream.removesuffix("/sigma")
        assert line["writer"] == {
            "type_name": "geometry_msgs::msg::dds_::WrenchStamped_",
            "user_data": f"typehash={rosbags_hash(RAW['WrenchStamped'])};",
        }
        assert len(line["messages"]) == 30, line["topic"]
        for m in line["messages"]:
            stamp = m["header"]["stamp"]
            sample = ref.samples[(stream, stamp["sec"] * 10**9 + stamp["nanosec"])]
            assert m["header"]["frame_id"] == frames[stream]
            w = m["wrench"]
            # float64 from end to end: exactly equal (the sigma's NaN where the daemon does not know it)
            np.testing.assert_array_equal(
                [w[p][a] for p in ("force", "torque") for a in "xyz"],
                sample.sigma if sigma else sample.values,
            )
            if sigma and stream.endswith("/compensated"):  # known once an orientation came, else NaN
                known = not sample.flags & wire.FLAG_INVALID
                assert np.all(np.asarray(sample.sigma) > 0) if known else np.all(np.isnan(sample.sigma))
            elif sigma:  # at rest on the simulated bus, every raw sample's sigma is known
                assert np.all(np.asarray(sample.sigma) > 0), sample.sigma


def test_diagnostics_name_the_daemon_each_sensor_and_each_chip(daemon):
    (line,) = peer(
        {"do": "read", "topics": {"rt/diagnostics": "DiagnosticArray"}, "count": 1, "reliable": True}
    )
    assert line["writer"]["type_name"] == "diagnostic_msgs::msg::dds_::DiagnosticArray_"
    assert line["writer"]["user_data"] == f"typehash={rosbags_hash(RAW['DiagnosticArray'])};"
    status = {s["name"]: s for s in line["messages"][0]["status"]}
    chips = [n for n in status if " chip 0x" in n]
    assert {f"{NS}: daemon", f"{NS}: sensor1", f"{NS}: sensor2"} <= set(status) and len(chips) == 16
    assert all(s["level"] == 0 for n, s in status.items() if n in chips)  # the simulated chips are all well
    values = {v["key"]: v["value"] for v in status[f"{NS}: sensor1"]["values"]}
    assert values["serial"] == "sim-sensor1" and values["chips_ok"] == "8 of 8"
    # the predicted sigma at rest, as `ftsensord status` prints it: three forces (N), three torques (mNm)
    forces, torques = values["predicted_sigma_at_rest"].split(" N, ")
    assert len(forces.split()) == 3 and torques.endswith(" mNm") and len(torques.split()) == 4
    assert all(float(v) > 0 for v in forces.split() + torques.split()[:3])
    assert status[f"{NS}: sensor1 chip 0x0C"]["hardware_id"] == "MLX90393 0x0C"


def test_ros2_node_list_finds_the_node_with_the_endpoints_discovery_finds(daemon):
    wrenches = [f"rt/{NS}/{s}" for s in STREAMS]
    (graph,) = peer({"do": "nodes", "topics": [*wrenches, f"rt/{NS}/tare", "rt/diagnostics"]})
    endpoints = graph["endpoints"]
    (bridge,) = {e["participant"] for t in wrenches for e in endpoints[t]}  # one participant has them all
    (node,) = graph["participants"][bridge]  # its ros_discovery_info: one node
    assert (node["namespace"], node["name"]) == (f"/{NS}", "ftsensord")
    for topic in wrenches + ["rt/diagnostics"]:  # the node's writer GIDs are the writers' own GUIDs
        assert [e["guid"] for e in endpoints[topic] if e["participant"] == bridge][0] in node["writers"], (
            topic
        )
    (tare,) = [e["guid"] for e in endpoints[f"rt/{NS}/tare"] if e["participant"] == bridge]
    assert tare in node["readers"] and tare not in node["writers"]
    assert (
        len(node["writers"]) == len(set(node["writers"])) >= 2 * len(STREAMS) + 2
    )  # + statuses, diagnostics, tare reply


def test_an_orientation_from_ros_reaches_the_gravity_compensation(daemon):
    folder = daemon[0]
    s45 = float(np.sqrt(0.5))
    out = peer(
        {
            "do": "publish",
            "topic": f"rt/{NS}/orientation/tip",
            "type": "QuaternionStamped",
            "times": 10,
            "period_s": 0.02,
            "message": {"stamp": [123, 456_000_000], "q_xyzw": [s45, 0.0, 0.0, s45]},
        },
        {
            "do": "publish",
            "topic": f"rt/{NS}/imu/sensor1",
            "type": "Imu",
            "times": 5,
            "period_s": 0.02,
            "message": {"stamp": [77, 0], "q_xyzw": [0.0, 0.0, 0.0, 1.0], "covariance0": -1.0},
        },
    )
    assert all(o["matched"] for o in out)
    gravity = ControlClient(f"ipc://{folder / 'control'}").status()["gravity"]
    assert gravity["stream"]["frames"]["tip"]["t_sender"] == pytest.approx(123.456)
    # 90 deg about x: the world's gravity [0, 0, -g] is along -y in the tip frame
    np.testing.assert_allclose(gravity["frames"]["tip"]["gravity_now_mps2"], [0.0, -9.80665, 0.0], atol=1e-5)
    assert "sensor1" not in gravity["stream"]["frames"]  # an Imu whose covariance[0] is -1 has no orientation
    # From the first on, the tip's compensated samples are valid, each with its sigma: the raw
    # one's and the stream's orientation noise through the tool's weight, in variance.
    ref = daemon[1]
    valid = [
        x
        for (topic, _), x in list(ref.samples.items())
        if topic == "wrench/tip/compensated" and not x.flags & wire.FLAG_INVALID
    ]
    assert valid
    for x in valid:
        raw = ref.samples[("wrench/tip", round(x.t_wall * 1e9))].sigma
        assert np.all(x.sigma >= raw) and np.any(x.sigma > raw), (x.sigma, raw)


def test_the_trigger_service_and_the_tare_topic_tare_the_sensors(daemon):
    folder, _ = daemon
    control = ControlClient(f"ipc://{folder / 'control'}")
    control.untare()
    # Under gravity compensation a tare needs orientations throughout: refused without, and said
    (reply,) = peer({"do": "trigger", "name": f"/{NS}/tare"})
    assert reply["available"] and reply["guid"] == reply["sent_guid"] and reply["seq"] == 7
    assert not reply["success"] and "orientation" in reply["message"], reply
    assert not any(s["tared"] for s in control.status()["sensors"].values())
    orient = [f"rt/{NS}/orientation/{f}" for f in ("sensor1", "sensor2", "tip")]
    reply, second = peer({"do": "trigger", "name": f"/{NS}/tare", "orient": orient, "requests": 2})
    assert reply["success"] and "tared sensor1" in reply["message"], reply
    # one tare at a time: the second request, sent while the first runs, is answered at once
    assert second["seq"] == 8 and not second["success"] and "under way" in second["message"], second
    assert all(s["tared"] for s in control.status()["sensors"].values())
    control.untare()
    assert not any(s["tared"] for s in control.status()["sensors"].values())
    (out,) = peer({"do": "trigger-topic", "topic": f"rt/{NS}/tare", "orient": orient})
    assert out["matched"] and out["tared"]  # as /diagnostics said it
    assert all(s["tared"] for s in control.status()["sensors"].values())


def test_a_ros2_table_is_checked_and_names_the_extra_when_it_is_missing(tmp_path, monkeypatch):
    path = write_config(tmp_path, extra='[ros2]\nnamespace = "9lives"\n')
    assert_names_file_and_key(load_config, path, "ros2.namespace", "a ROS 2 name")
    path = write_config(tmp_path, extra="[ros2]\ndomain_id = 300\n")
    assert_names_file_and_key(load_config, path, "ros2.domain_id", "0 to 232")
    path = write_config(tmp_path, extra='[ros2]\noutput = "thread"\n')
    assert_names_file_and_key(load_config, path, "ros2.output", '"in-loop" or "bridge"')
    monkeypatch.setenv("ROS_DOMAIN_ID", "42")
    assert load_config(write_config(tmp_path, extra="[ros2]\n")).ros2.domain_id == 42
    assert (
        load_config(write_config(tmp_path, extra="[ros2]\n")).ros2.output == "in-loop"
    )  # the default: measured
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "cyclonedds" else real(name, *a)
    )
    with pytest.raises(Exception, match=r"ftsensord\.toml: ros2: .*pip install 'ftsensord\[ros2\]'"):
        load_config(write_config(tmp_path, extra="[ros2]\n"))


def test_a_failing_chip_or_a_flagged_wrench_raises_the_level_ros_tools_show():
    from ftsensord.protocol import wire
    from ftsensord.ros2 import diagnostics as d

    chips = {
        "0x0C": {"sensor": "s1", "state": "ok", "last_error": None},
        "0x0D": {"sensor": "s1", "state": "failing", "last_error": "NACK"},
    }
    status = {
        "rate_hz": 100.0,
        "achieved_rate_hz": 99.9,
        "bus": "sim",
        "chips": chips,
        "sensors": {"s1": {"serial": "x", "temperature": {"beyond_span": False}}},
    }
    levels = {name: level for level, name, *_ in d.statuses(status, {"s1": 0}, "ns")}
    assert levels == {
        "ns: daemon": d.OK,
        "ns: s1": d.ERROR,
        "ns: s1 chip 0x0C": d.OK,
        "ns: s1 chip 0x0D": d.ERROR,
    }
    chips["0x0D"]["state"] = "ok"
    for flags, level in (
        (0, d.OK),
        (wire.FLAG_LATE, d.OK),
        (wire.FLAG_DEGRADED, d.WARN),
        (wire.FLAG_INVALID, d.ERROR),
    ):
        (sensor,) = [s for s in d.statuses(status, {"s1": flags}, "ns") if s[1] == "ns: s1"]
        assert sensor[0] == level, (flags, sensor)
    status["achieved_rate_hz"] = 90.0  # below 95 % of the rate
    assert d.statuses(status, {}, "ns")[0][0] == d.WARN
    assert d.statuses(None, {}, "ns", "timed out") == [
        (d.STALE, "ns: daemon", "no answer from the daemon: timed out", "", [])
    ]


def test_the_in_loop_diagnostics_show_what_the_status_reply_says(tmp_path):
    """In the loop's thread the statuses come from `health_reply`, not the whole `status` reply:
    the same statuses, with a chip failing too."""
    from ftsensord.daemon.status import health_reply
    from ftsensord.protocol import wire
    from ftsensord.ros2 import diagnostics as d

    rig = Rig(tmp_path)
    try:
        rig.bus.faults.nack(0x0E)
        rig.cycles(3)
        health, status = health_reply(rig.daemon), rig.daemon.status()
        assert health == {k: status[k] for k in health}
        flags = {"sensor1": wire.FLAG_CHIP_MISSING, "sensor2": 0}
        shown = d.statuses(health, flags, "ns")
        assert shown == d.statuses(status, flags, "ns")
        assert {name: level for level, name, *_ in shown if level} == {
            "ns: sensor1": d.ERROR,
            "ns: sensor1 chip 0x0E": d.ERROR,
        }
    finally:
        rig.close()


def test_the_bridge_stops_with_the_daemon_even_when_it_is_killed(tmp_path):
    config = write_config(
        tmp_path, extra=f'[ros2]\nnamespace = "{NS}_kill"\ndomain_id = {DOMAIN}\noutput = "bridge"\n'
    )
    proc, notify = start_daemon(config, tmp_path, env={"CYCLONEDDS_URI": URI})
    try:
        (child,) = Path(f"/proc/{proc.pid}/task/{proc.pid}/children").read_text().split()
        assert "ros2" in Path(f"/proc/{child}/cmdline").read_text()
    finally:
        proc.kill()  # SIGKILL: the daemon has no say; the kernel's PR_SET_PDEATHSIG stops the bridge
        proc.wait()
        notify.close()
    end = time.monotonic() + 10  # the bridge's SIGTERM handling: its loops look every 0.2 s
    while time.monotonic() < end and process_state(child) not in ("Z", "gone"):
        time.sleep(0.05)
    assert process_state(child) in ("Z", "gone")  # a zombie: exited, its parent (dead) not reaping it


def process_state(pid: str) -> str:
    """/proc's state letter of ``pid`` ("Z": exited, not yet reaped), "gone" when there is none."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return "gone"


@pytest.mark.parametrize("frame_id", ["", "a", "tip", "sensor1", "sensor1/chip0", "é_unicode"])
def test_the_bridges_cdr_bytes_are_cyclones_own_serialization(frame_id):
    from ftsensord.recording.ros2mcap import Stamped, stamp, status_body
    from ftsensord.ros2 import msgs

    t_wall, values = 1_764_100_000.123456789, [1.5, -2.25, 3e-3, -4e5, 5.0, float("nan")]
    header = msgs.Header(msgs.Time(*stamp(t_wall)), frame_id)
    wrench = msgs.WrenchStamped(header, msgs.Wrench(msgs.Vector3(*values[:3]), msgs.Vector3(*values[3:])))
    # the frame's padding to the first float64 depends on the frame_id's length: each length is one case
    assert Stamped(frame_id).message(t_wall, np.array(values).tobytes()) == wrench.serialize(
        use_version_2=False
    )
    status = msgs.SampleStatus(header, 2**40 + 3, 0x41, 7)
    assert Stamped(frame_id).message(t_wall, status_body(2**40 + 3, 0x41, 7)) == status.serialize(
        use_version_2=False
    )


@pytest.mark.parametrize(
    "statuses",
    [
        [],
        [(0, "ns: daemon", "100 Hz", "", [])],
        [
            (3, "ns: daemon", "no answer", "", []),
            (
                2,
                "ns: s1 chip 0x0D",
                "failing: NACK",
                "MLX90393 0x0D",
                [("state", "failing"), ("errors", "12"), ("é", "")],
            ),
        ],
        [(1, "n" * k, "m" * (k + 1), "h" * (k + 2), [("k" * k, "v" * (k + 3))] * k) for k in range(6)],
    ],
)
def test_the_diagnostics_cdr_bytes_are_cyclones_own_serialization(statuses):
    from ftsensord.recording.ros2mcap import stamp
    from ftsensord.ros2 import diagnostics, msgs

    t_wall = 1_764_100_000.987654321
    array = msgs.DiagnosticArray(
        msgs.Header(msgs.Time(*stamp(t_wall)), ""),
        [
            msgs.DiagnosticStatus(level, name, message, hardware_id, [msgs.KeyValue(k, v) for k, v in values])
            for level, name, message, hardware_id, values in statuses
        ],
    )
    # the strings' lengths 0-5 move every later length's 4-byte alignment: each is a case
    assert diagnostics.cdr(statuses, t_wall) == array.serialize(use_version_2=False)
    for count in (1, 2):  # a few statuses a cycle, as the in-loop output encodes them
        encoder, adds = diagnostics.Encoder(statuses), 1
        while not encoder.add(count):
            adds += 1
        assert encoder.message(t_wall) == array.serialize(use_version_2=False)
        assert adds == max(1, -(-len(statuses) // count))  # no add more than the statuses need


def can_be_realtime() -> bool:
    return subprocess.run(["chrt", "-f", "1", "true"], capture_output=True).returncode == 0


@pytest.mark.skipif(
    not can_be_realtime(), reason="SCHED_FIFO not allowed here (needs CAP_SYS_NICE or RLIMIT_RTPRIO)"
)
def test_under_a_realtime_daemon_only_the_bridges_forwarding_is_realtime_below_the_loop(tmp_path):
    config = write_config(
        tmp_path, extra=f'[ros2]\nnamespace = "{NS}_rt"\ndomain_id = {DOMAIN}\noutput = "bridge"\n'
    )
    proc, notify = start_daemon(config, tmp_path, env={"CYCLONEDDS_URI": URI}, args=["--realtime", "50"])
    try:
        (child,) = Path(f"/proc/{proc.pid}/task/{proc.pid}/children").read_text().split()
        end = (
            time.monotonic() + 30
        )  # the bridge's start: imports, the daemon's status, the node, then the raise
        while time.monotonic() < end and os.sched_getscheduler(int(child)) != os.SCHED_FIFO:
            time.sleep(0.1)
        time.sleep(0.5)  # its ZeroMQ context made just after the raise
        threads = {
            int(t): Path(f"/proc/{child}/task/{t}/comm").read_text().strip()
            for t in os.listdir(f"/proc/{child}/task")
        }
        policy = {t: (os.sched_getscheduler(t), os.sched_getparam(t).sched_priority) for t in threads}
        assert (os.sched_getscheduler(proc.pid), os.sched_getparam(proc.pid).sched_priority) == (
            os.SCHED_FIFO,
            50,
        )
        assert policy[int(child)] == (os.SCHED_FIFO, 1), threads  # the forwarding (main) thread
        assert any(
            policy[t] == (os.SCHED_FIFO, 1) for t, name in threads.items() if name.startswith("ZMQbg/IO")
        )
        others = {
            name: policy[t] for t, name in threads.items() if t != int(child) and not name.startswith("ZMQbg")
        }
        assert len(others) >= 3 and all(p == (os.SCHED_OTHER, 0) for p in others.values()), (
            others
        )  # DDS's, inputs
    finally:
        proc.terminate()
        proc.wait(timeout=20)
        notify.close()


@pytest.mark.skipif(
    not can_be_realtime(), reason="SCHED_FIFO not allowed here (needs CAP_SYS_NICE or RLIMIT_RTPRIO)"
)
def test_in_loop_under_a_realtime_daemon_ddss_own_threads_stay_at_the_normal_policy(tmp_path):
    config = write_config(
        tmp_path, extra=f'[ros2]\nnamespace = "{NS}_rt"\ndomain_id = {DOMAIN}\noutput = "in-loop"\n'
    )
    proc, notify = start_daemon(config, tmp_path, env={"CYCLONEDDS_URI": URI}, args=["--realtime", "50"])
    try:
        assert not Path(f"/proc/{proc.pid}/task/{proc.pid}/children").read_text().split()  # no bridge process
        threads = {
            int(t): Path(f"/proc/{proc.pid}/task/{t}/comm").read_text().strip()
            for t in os.listdir(f"/proc/{proc.pid}/task")
        }
        policy = {t: (os.sched_getscheduler(t), os.sched_getparam(t).sched_priority) for t in threads}
        assert policy[proc.pid] == (os.SCHED_FIFO, 50)  # the loop's thread, which makes the DDS writes
        dds = {
            name: policy[t]
            for t, name in threads.items()
            if name in ("gc", "dq.builtins", "dq.user", "tev", "recv")
        }
        assert len(dds) == 5 and all(p == (os.SCHED_OTHER, 0) for p in dds.values()), (dds, threads)
    finally:
        proc.terminate()
        proc.wait(timeout=20)
        notify.close()


def test_in_loop_without_a_dds_participant_the_zeromq_streams_go_on(tmp_path):
    """A Cyclone DDS configuration it cannot use (an interface this host does not have): the
    daemon says so in its log and publishes on ZeroMQ as without ``[ros2]``."""
    config = write_config(tmp_path, extra=f'[ros2]\nnamespace = "{NS}_bad"\ndomain_id = {DOMAIN}\n')
    bad = (
        "<CycloneDDS><Domain Id='any'><General><Interfaces><NetworkInterface address='192.0.2.77'/>"
        "</Interfaces></General></Domain></CycloneDDS>"
    )  # TEST-NET-1: never a local address
    log = tmp_path / "log"
    with log.open("w") as out:
        proc, notify = start_daemon(config, tmp_path, env={"CYCLONEDDS_URI": bad}, stderr=out)
    try:
        ref = Reference(f"ipc://{tmp_path / 'ftsensord' / 'wrench'}")
        ref.start()
        time.sleep(1.0)
        ref.stop.set()
        assert len(ref.samples) > 50  # 100 Hz, two streams: ZeroMQ unaffected
        assert proc.poll() is None
    finally:
        proc.terminate()
        proc.wait(timeout=20)
        notify.close()
    text = log.read_text()
    assert "the ROS 2 output did not start: ros2: no DDS participant on domain" in text, text[-2000:]


def test_a_frame_that_is_not_a_wrench_is_dropped_and_counted():
    """On a wrench stream, garbage and a sample of another kind are dropped and counted (the
    first logged), never written to DDS; a wrench is written and handed on for its status."""
    from types import SimpleNamespace

    from ftsensord.protocol import wire
    from ftsensord.ros2.bridge import Bridge

    written: list[tuple] = []
    bridge = SimpleNamespace(
        bad_frames=0,
        endpoint="ipc://test",
        node=SimpleNamespace(publish_wrench=lambda *args: written.append(args)),
        sigmas=[],
    )
    flux = wire.encode("wrench/sensor1", wire.KIND_FLUX, 1, 0.0, 0.0, 0, np.zeros(24))
    assert Bridge.forward(bridge, flux) is None and Bridge.forward(bridge, b"garbage") is None
    assert bridge.bad_frames == 2 and not written
    wrench = wire.encode("wrench/sensor1", wire.KIND_WRENCH, 2, 1.0, 5.0, 3, np.arange(6.0))
    assert Bridge.forward(bridge, wrench) == ("wrench/sensor1", 5.0, 2, 3)
    assert len(written) == 1 and written[0][2] == np.arange(6.0).tobytes()
    # A wrench's sigma (its companion, sent before it) is kept to be written after the cycle's wrenches.
    sigma = wire.encode("sigma/wrench/sensor1", wire.KIND_SIGMA, 3, 1.0, 6.0, 3, np.full(6, 0.01))
    assert Bridge.forward(bridge, sigma) is None and bridge.bad_frames == 2 and len(written) == 1
    assert bridge.sigmas == [("wrench/sensor1", 6.0, np.full(6, 0.01).tobytes())]
