"""`ftsensord bridge` against `ftsensord run` on the simulated bus, read by a client of the
Foxglove WebSocket protocol (subprotocol foxglove.sdk.v1, the SDK's; serverInfo and advertise as
JSON, a subscribe request, then binary Message Data frames: opcode 1, u32 subscription id,
u64 log time in ns, the message) over the websockets library, the messages decoded with
mcap_ros2's ROS 2 CDR decoder. Checked against a Python `Subscriber` receiving in parallel."""

from __future__ import annotations

import json
import os
import signal
import socket
import struct
import subprocess
import sys
import threading
import time

import pytest

from ftsensord.client import ControlClient, Subscriber
from ftsensord.recording.ros2mcap import stamp

from .test_daemon import write_config

pytest.importorskip("foxglove")
websockets_sync = pytest.importorskip("websockets.sync.client")
from mcap.records import Schema  # noqa: E402  (the record extra, with the tests)
from mcap_ros2.decoder import DecoderFactory  # noqa: E402

STREAMS = ["wrench/sensor1", "wrench/tip"]


@pytest.fixture
def daemon(tmp_path):
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(tmp_path / "notify"))
    notify.settimeout(30)
    env = {**os.environ, "XDG_RUNTIME_DIR": str(tmp_path), "NOTIFY_SOCKET": str(tmp_path / "notify")}
    env.pop("RUNTIME_DIRECTORY", None)
    proc = subprocess.Popen([sys.executable, "-m", "ftsensord", "run", "--config", str(write_config(tmp_path))],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        assert notify.recv(4096).startswith(b"READY=1")
        yield tmp_path / "ftsensord"
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=20)
        notify.close()


class Reference(threading.Thread):
    """Every sample of the streams, by (topic, seq), as the Python client receives them."""

    def __init__(self, endpoint: str):
        super().__init__(daemon=True)
        self.endpoint, self.samples, self.stop = endpoint, {}, threading.Event()

    def run(self) -> None:
        with Subscriber(self.endpoint, STREAMS) as sub:
            while not self.stop.is_set():
                s = sub.receive(timeout_s=0.05)
                if s is not None:
                    self.samples[(s.topic, s.seq)] = s


def test_a_foxglove_client_gets_the_streams_as_ros2_messages_at_the_samples_time(daemon):
    pub = f"ipc://{daemon / 'wrench'}"
    frames = ControlClient(f"ipc://{daemon / 'control'}").status()["frames"]
    ref = Reference(pub)
    ref.start()
    bridge = subprocess.Popen([sys.executable, "-m", "ftsensord", "bridge", *STREAMS, "--port", "0", "--endpoint", pub],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = bridge.stdout.readline()
        port = int(line.split("ws://127.0.0.1:")[1].split()[0])
        messages = foxglove_client(port, {f"/{s}" for s in STREAMS} | {f"/{s}/status" for s in STREAMS}, 60)
    finally:
        bridge.send_signal(signal.SIGINT)
        _, err = bridge.communicate(timeout=20)
        ref.stop.set()
        ref.join()
    assert bridge.returncode == 0 and "Traceback" not in err and "(stopped by SIGINT)" in err, err
    # Each wrench and its status come as a pair from one sample: match them by stamp.
    status = {(topic[1:-len("/status")], log_time): msg for topic, log_time, msg, _ in messages
              if topic.endswith("/status")}
    checked = 0
    for topic, log_time, msg, schema in messages:
        if topic.endswith("/status"):
            assert schema == "ftsensord_msgs/msg/SampleStatus"
            continue
        assert schema == "geometry_msgs/msg/WrenchStamped"
        st = status.get((topic[1:], log_time))
        if st is None:
            continue  # the last wrenches' statuses came after the client stopped reading
        sample = ref.samples[(topic[1:], st.seq)]
        assert st.flags == sample.flags
        sec, nanosec = stamp(sample.t_wall)
        assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (sec, nanosec)
        assert log_time == sec * 10**9 + nanosec  # the sample's own time, not the arrival's
        assert msg.header.frame_id == frames[topic[1:]]
        w = msg.wrench
        assert [w.force.x, w.force.y, w.force.z, w.torque.x, w.torque.y, w.torque.z] == sample.values.tolist()
        checked += 1
    assert checked >= 40


def foxglove_client(port: int, topics: set[str], count: int) -> list[tuple[str, int, object, str]]:
    """Subscribe to ``topics`` as a Foxglove WebSocket client; (topic, log_time_ns, decoded
    message, schema name) of the first ``count`` wrench messages and their statuses."""
    decoders = DecoderFactory()
    with websockets_sync.connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"],
                                 open_timeout=10) as ws:
        channels: dict[int, dict] = {}
        subscribed: dict[int, dict] = {}
        out: list[tuple[str, int, object, str]] = []
        deadline = time.monotonic() + 20
        while sum(not t.endswith("/status") for t, *_ in out) < count and time.monotonic() < deadline:
            frame = ws.recv(timeout=5)
            if isinstance(frame, str):
                msg = json.loads(frame)
                if msg["op"] == "advertise":
                    new = [c for c in msg["channels"] if c["topic"] in topics and c["id"] not in channels]
                    for c in new:
                        channels[c["id"]] = c
                        subscribed[len(subscribed) + 1] = c
                    ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                        {"id": sid, "channelId": c["id"]} for sid, c in subscribed.items() if c in new]}))
                continue
            opcode, sid, log_time = struct.unpack_from("<BIQ", frame)
            assert opcode == 1  # Message Data
            c = subscribed[sid]
            assert c["encoding"] == "cdr" and c["schemaEncoding"] == "ros2msg"
            schema = Schema(id=c["id"], name=c["schemaName"], encoding="ros2msg", data=c["schema"].encode())
            decoded = decoders.decoder_for("cdr", schema)(frame[13:])
            out.append((c["topic"], log_time, decoded, c["schemaName"]))
    return out
