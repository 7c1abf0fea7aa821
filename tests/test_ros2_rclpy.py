"""The streams on the graph of real ROS 2: rclpy with its default rmw (rmw_fastrtps_cpp) on
Jazzy (Fast DDS 2.14) and Kilted (Fast DDS 3.2), each from its own wheels
(tests/ros2_venvs.py), as a ROS 2 user's node (tests/ros2_rclpy_peer.py) against `ftsensord
run` with a ``[ros2]`` table. What rclpy cannot show (the SampleStatus values: no package has
that message; the Trigger service over rmw_cyclonedds) is tests/test_ros2.py's Cyclone peer's.

Two daemons on one domain, two namespaces: the in-loop output (the default) and the bridge.
Isolation as tests/test_ros2.py: a domain of this module's own, Cyclone on the loopback by
unicast, the ROS 2 peers' discovery kept to this host (ROS_AUTOMATIC_DISCOVERY_RANGE).
"""

from __future__ import annotations

import json
import os
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("cyclonedds")  # the ros2 extra, which the test extra includes

from ftsensord.client import ControlClient  # noqa: E402

from .conftest import StreamRecorder, start_daemon  # noqa: E402
from .ros2_venvs import DISTRIBUTIONS, PEER, peer_env, python_of  # noqa: E402
from .test_daemon import write_config  # noqa: E402
from .test_ros2 import GRAVITY, URI  # noqa: E402

DOMAIN = 1 + os.getpid() % 99  # 1-99: clear of ROS's default 0 and of tests/test_ros2.py's 100-199
NS, NS_BRIDGE = "fts_rclpy", "fts_rclpy_bridge"
STREAMS = ["wrench/sensor1", "wrench/tip"]
#: What the daemon's log must never say to a well-formed peer (Cyclone's own warnings: a type
#: it rejects, a sample it could not read; the daemon's: an output that failed).
BAD_LOG = ("invalid type object", "deserialization", "ERROR", "WARNING", "failed")
#: Where rclpy cannot tell which node has the daemon's endpoints: Kilted's rmw_fastrtps takes an
#: endpoint's participant from its discovery data's PID_PARTICIPANT_GUID, which Cyclone DDS
#: leaves out (DDSI-RTPS allows it: the endpoint's GUID has the participant's prefix) and Fast
#: DDS 3.2 does not fill in; Jazzy's takes the prefix. The node itself is listed on both.
UNATTRIBUTED = {"kilted"}


class Daemon:
    """`ftsensord run` with a ``[ros2]`` table, its log in a file, its samples as the Python
    client receives them by (stream, stamp in ns)."""

    def __init__(self, folder: Path, namespace: str, output: str):
        self.folder, self.namespace = folder, namespace
        config = write_config(
            folder,
            extra=f'[ros2]\nnamespace = "{namespace}"\ndomain_id = {DOMAIN}\noutput = "{output}"\n' + GRAVITY,
        )
        self.log = folder / "daemon.log"
        with open(self.log, "w") as log:
            self.proc, self.notify = start_daemon(
                config, folder, env={"CYCLONEDDS_URI": URI}, stdout=log, stderr=subprocess.STDOUT
            )
        self.control = ControlClient(f"ipc://{folder / 'ftsensord' / 'control'}")
        self.ref = StreamRecorder(
            f"ipc://{folder / 'ftsensord' / 'wrench'}", STREAMS, lambda s: (s.topic, round(s.t_wall * 1e9))
        )
        self.ref.start()

    def close(self) -> None:
        self.ref.stop.set()
        self.ref.join(timeout=5)
        self.proc.terminate()
        self.proc.wait(timeout=20)
        self.notify.close()


@pytest.fixture(scope="module", params=sorted(DISTRIBUTIONS))
def ros2(request) -> Path:
    """A distribution's Python with rclpy (its environment made on first use). Under CI an
    environment that cannot be made fails the tests; elsewhere (no index reachable) skips them."""
    try:
        return python_of(request.param)
    except (RuntimeError, subprocess.TimeoutExpired) as exc:
        if os.environ.get("CI"):
            raise
        pytest.skip(f"no ROS 2 {request.param} environment: {exc}")


@pytest.fixture(scope="module")
def daemons(tmp_path_factory) -> Iterator[tuple[Daemon, Daemon]]:
    """Two daemons on one domain: ``NS`` in-loop, ``NS_BRIDGE`` by the bridge process."""
    started = []
    try:
        for namespace, output in ((NS, "in-loop"), (NS_BRIDGE, "bridge")):
            started.append(Daemon(tmp_path_factory.mktemp(namespace), namespace, output))
        yield started[0], started[1]
    finally:
        for d in started:
            d.close()


def peer(python: Path, *steps: dict, timeout_s: float = 90) -> list[dict]:
    """The rclpy node run with ``steps``; its JSON lines."""
    done = subprocess.run(
        [str(python), str(PEER), str(DOMAIN), json.dumps(list(steps))],
        env=peer_env(),
        capture_output=True,
        text=True,
        timeout=timeout_s,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return [json.loads(line) for line in done.stdout.splitlines()]


def test_ros2_lists_each_daemons_node_its_topics_and_which_node_publishes_them(ros2, daemons):
    topics = {
        f"/{ns}/{s}{tail}" for ns in (NS, NS_BRIDGE) for s in STREAMS for tail in ("", "/status", "/sigma")
    }
    graphs = peer(
        ros2,
        *(
            {
                "do": "graph",
                "node_fqn": f"/{ns}/ftsensord",
                "topics": sorted(topics),
                "timeout_s": 30,
                "subscribed": [f"/{ns}/tare", f"/{ns}/orientation/tip", f"/{ns}/imu/sensor1"],
            }
            for ns in (NS, NS_BRIDGE)
        ),
    )
    graph = graphs[-1]  # after both nodes were seen
    assert {(f"/{ns}", "ftsensord") for ns in (NS, NS_BRIDGE)} <= {(n[1], n[0]) for n in graph["nodes"]}
    types = graph["topics"]
    for ns in (NS, NS_BRIDGE):
        for s in STREAMS:
            assert types[f"/{ns}/{s}"] == ["geometry_msgs/msg/WrenchStamped"]
            assert types[f"/{ns}/{s}/status"] == ["ftsensord_msgs/msg/SampleStatus"]
            assert types[f"/{ns}/{s}/sigma"] == ["geometry_msgs/msg/WrenchStamped"]  # a standard type
            assert types[f"/{ns}/{s}/compensated"] == ["geometry_msgs/msg/WrenchStamped"]
            assert types[f"/{ns}/{s}/compensated/sigma"] == ["geometry_msgs/msg/WrenchStamped"]
        assert types[f"/{ns}/tare"] == ["std_msgs/msg/Empty"]
        assert types[f"/{ns}/orientation/tip"] == ["geometry_msgs/msg/QuaternionStamped"]
        assert types[f"/{ns}/imu/sensor1"] == ["sensor_msgs/msg/Imu"]
    assert types["/diagnostics"] == ["diagnostic_msgs/msg/DiagnosticArray"]
    # every topic's publisher is its own daemon's node, never the other's (nor a bare DDS app)
    bare = ("_CREATED_BY_BARE_DDS_APP_", "_CREATED_BY_BARE_DDS_APP_")
    distro = ros2.parent.parent.name
    for topic in topics:
        (pub,) = graph["publishers"][topic]
        owner = bare if distro in UNATTRIBUTED else ("/" + topic.split("/")[1], "ftsensord")
        assert (pub["node_namespace"], pub["node_name"]) == owner, pub
        assert pub["reliability"] == "reliable" and pub["durability"] == "volatile"
    for g, ns in zip(graphs, (NS, NS_BRIDGE)):  # and the inputs' readers are the node's
        for topic, subs in g["subscribers"].items():
            owner = bare if distro in UNATTRIBUTED else (f"/{ns}", "ftsensord")
            assert [(s["node_namespace"], s["node_name"]) for s in subs] == [owner], topic


@pytest.mark.parametrize("which", [0, 1], ids=["in-loop", "bridge"])
def test_a_default_and_a_sensor_data_subscriber_read_each_wrench_as_the_zeromq_stream_has_it(
    ros2, daemons, which
):
    daemon = daemons[which]
    ns = (NS, NS_BRIDGE)[which]
    frames = daemon.control.status()["frames"]
    # each wrench and its sigma, stamped and framed as it
    topics = {f"/{ns}/{s}{tail}": "WrenchStamped" for s in STREAMS for tail in ("", "/sigma")}
    lines = peer(
        ros2,
        {"do": "read", "topics": topics, "count": 100, "qos": "default"},
        {"do": "read", "topics": topics, "count": 100, "qos": "sensor_data"},
    )
    time.sleep(0.1)  # the reference's last samples in
    assert len(lines) == 2 * len(topics)
    for line in lines:
        stream = line["topic"].removeprefix(f"/{ns}/")
        sigma = stream.endswith("/sigma")
        stream = stream.removesuffix("/sigma")
        assert len(line["messages"]) == 100, line["topic"]
        stamps = []
        for m in line["messages"]:
            stamp = m["header"]["stamp"]
            stamps.append(stamp["sec"] * 10**9 + stamp["nanosec"])
            sample = daemon.ref.samples[(stream, stamps[-1])]
            assert m["header"]["frame_id"] == frames[stream]
            w = m["wrench"]
            # float64 from end to end: exactly equal (the sigma's NaN where the daemon does not know it)
            np.testing.assert_array_equal(
                [w[p][a] for p in ("force", "torque") for a in "xyz"],
                sample.sigma if sigma else sample.values,
            )
        assert stamps == sorted(set(stamps))  # in order, none twice


def test_diagnostics_reach_rclpy_with_the_daemon_each_sensor_and_each_chip(ros2, daemons):
    (line,) = peer(ros2, {"do": "read", "topics": {"/diagnostics": "DiagnosticArray"}, "count": 4})
    names = [{s["name"] for s in m["status"]} for m in line["messages"]]
    for ns in (NS, NS_BRIDGE):  # both daemons publish /diagnostics, each its own statuses
        # Each daemon publishes once a second: among 4 messages each has one (two in a row may
        # be the same daemon's when the reader starts between them).
        own = next((n for n in names if f"{ns}: daemon" in n), None)
        assert own is not None and {f"{ns}: sensor1", f"{ns}: sensor2"} <= own, names
        assert len([n for n in own if " chip 0x" in n]) == 16
    status = {s["name"]: s for m in line["messages"] for s in m["status"]}
    assert status[f"{NS}: sensor1 chip 0x0C"]["hardware_id"] == "MLX90393 0x0C"
    assert status[f"{NS}: sensor1 chip 0x0C"]["level"] in (0, [0], b"\0")  # rclpy gives a byte field as bytes


def test_orientations_from_rclpy_reach_the_gravity_compensation(ros2, daemons):
    daemon = daemons[0]
    s45 = float(np.sqrt(0.5))
    # one frame at a time: the tip's orientation follows from a sensor's and the other way round
    (out,) = peer(
        ros2,
        {
            "do": "publish",
            "topic": f"/{NS}/orientation/tip",
            "type": "QuaternionStamped",
            "times": 10,
            "period_s": 0.02,
            "message": {"stamp": [123, 456_000_000], "q_xyzw": [s45, 0.0, 0.0, s45]},
        },
    )
    gravity = daemon.control.status()["gravity"]
    assert out["matched"] and gravity["stream"]["frames"]["tip"]["t_sender"] == pytest.approx(123.456)
    # 90 deg about x: the world's gravity [0, 0, -g] is along -y in the tip frame
    np.testing.assert_allclose(gravity["frames"]["tip"]["gravity_now_mps2"], [0.0, -9.80665, 0.0], atol=1e-5)
    before = gravity["stream"]["frames"].get("sensor2")  # (an earlier test's orientation, or none)
    out = peer(
        ros2,
        {
            "do": "publish",
            "topic": f"/{NS}/imu/sensor1",
            "type": "Imu",
            "times": 10,
            "period_s": 0.02,
            "message": {"stamp": [77, 250_000_000], "q_xyzw": [0.0, s45, 0.0, s45]},
        },
        {
            "do": "publish",
            "topic": f"/{NS}/imu/sensor2",
            "type": "Imu",
            "times": 5,
            "period_s": 0.02,
            "message": {"stamp": [78, 0], "q_xyzw": [0.0, 0.0, 0.0, 1.0], "covariance0": -1.0},
        },
    )
    gravity = daemon.control.status()["gravity"]
    frames = gravity["stream"]["frames"]
    assert all(o["matched"] for o in out) and frames["sensor1"]["t_sender"] == pytest.approx(77.25)
    # 90 deg about y: along +x in sensor1's frame
    np.testing.assert_allclose(
        gravity["frames"]["sensor1"]["gravity_now_mps2"], [9.80665, 0.0, 0.0], atol=1e-5
    )
    # an Imu whose covariance[0] is -1 has no orientation: sensor2's is what it was
    assert (frames.get("sensor2") or {}).get("t_sender") == (before or {}).get("t_sender")


def test_an_empty_message_from_rclpy_tares_the_sensors(ros2, daemons):
    daemon = daemons[0]
    daemon.control.untare()
    assert not any(s["tared"] for s in daemon.control.status()["sensors"].values())
    orient = [f"/{NS}/orientation/{f}" for f in ("sensor1", "sensor2", "tip")]
    (out,) = peer(ros2, {"do": "tare-topic", "topic": f"/{NS}/tare", "orient": orient})
    assert out["matched"] and out["tared"], out  # as /diagnostics, read by rclpy, said it
    assert all(s["tared"] for s in daemon.control.status()["sensors"].values())
    daemon.control.untare()


def test_the_daemons_log_nothing_wrong_for_these_peers(ros2, daemons):
    """Last in this module: after every peer above (of this distribution) came and went."""
    for daemon in daemons:
        text = daemon.log.read_text()
        assert "ready" in text  # the log is the daemon's
        bad = [line for line in text.splitlines() if any(b in line for b in BAD_LOG)]
        assert not bad, bad


def test_the_trigger_service_is_not_answered_to_an_rmw_fastrtps_client(ros2, tmp_path):
    """What docs/guide/ros2.md says: the service's request id travels in rmw_fastrtps's sample
    identities (RTPS inline QoS), which Cyclone DDS neither reads nor writes. rclpy sees the
    service (its topics match by name), its request is dropped, no tare happens; the Empty
    topic is the way to tare from the default rmw."""
    daemon = Daemon(tmp_path, f"{NS}_trigger", "in-loop")
    try:
        daemon.control.untare()
        orient = [f"/{daemon.namespace}/orientation/{f}" for f in ("sensor1", "sensor2", "tip")]
        (out,) = peer(
            ros2, {"do": "trigger", "name": f"/{daemon.namespace}/tare", "orient": orient, "timeout_s": 5}
        )
        assert out["available"] and not out["answered"], out
        assert not any(s["tared"] for s in daemon.control.status()["sensors"].values())
    finally:
        daemon.close()
    assert (
        "rq/fts_rclpy_trigger/tareRequest/std_srvs::srv::dds_::Trigger_Request_ failed"
        in daemon.log.read_text()
    )
