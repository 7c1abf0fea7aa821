"""A ROS 2 peer over Cyclone DDS, for tests/test_ros2.py: run as a separate process, nothing
imported from ftsensord. Its types are written here from ROS 2's message files (each
class quotes its .msg), named as every rmw names them (``<pkg>::msg::dds_::<Type>_``); the
Trigger service's wire types as rmw_cyclonedds carries them (a ``{uint64 guid; int64 seq}``
prefix, rmw_cyclonedds_cpp/src/serdata.hpp ``cdds_request_header_t``).

    python ros2_peer.py DOMAIN PLAN_JSON     (one JSON line out per result)
"""

import json
import sys
import threading
import time
from dataclasses import asdict, dataclass

from cyclonedds.builtin import BuiltinDataReader, BuiltinTopicDcpsPublication, BuiltinTopicDcpsSubscription
from cyclonedds.core import Policy, Qos
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import (
    array,
    bounded_str,
    byte,
    float64,
    int32,
    int64,
    sequence,
    uint8,
    uint32,
    uint64,
)
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic


@dataclass
class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: int32  # builtin_interfaces/msg/Time: int32 sec, uint32 nanosec
    nanosec: uint32


@dataclass
class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time  # std_msgs/msg/Header: builtin_interfaces/Time stamp, string frame_id
    frame_id: str


@dataclass
class Vector3(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
    x: float64  # geometry_msgs/msg/Vector3: float64 x, y, z
    y: float64
    z: float64


@dataclass
class Wrench(IdlStruct, typename="geometry_msgs::msg::dds_::Wrench_"):
    force: Vector3  # geometry_msgs/msg/Wrench: Vector3 force, Vector3 torque
    torque: Vector3


@dataclass
class WrenchStamped(IdlStruct, typename="geometry_msgs::msg::dds_::WrenchStamped_"):
    header: Header  # geometry_msgs/msg/WrenchStamped: std_msgs/Header header, Wrench wrench
    wrench: Wrench


@dataclass
class Quaternion(IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
    x: float64  # geometry_msgs/msg/Quaternion: float64 x 0, y 0, z 0, w 1
    y: float64
    z: float64
    w: float64


@dataclass
class QuaternionStamped(IdlStruct, typename="geometry_msgs::msg::dds_::QuaternionStamped_"):
    header: Header  # geometry_msgs/msg/QuaternionStamped: std_msgs/Header header, Quaternion quaternion
    quaternion: Quaternion


@dataclass
class Imu(IdlStruct, typename="sensor_msgs::msg::dds_::Imu_"):
    header: Header  # sensor_msgs/msg/Imu
    orientation: Quaternion
    orientation_covariance: array[float64, 9]
    angular_velocity: Vector3
    angular_velocity_covariance: array[float64, 9]
    linear_acceleration: Vector3
    linear_acceleration_covariance: array[float64, 9]


@dataclass
class KeyValue(IdlStruct, typename="diagnostic_msgs::msg::dds_::KeyValue_"):
    key: str  # diagnostic_msgs/msg/KeyValue: string key, string value
    value: str


@dataclass
class DiagnosticStatus(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticStatus_"):
    # diagnostic_msgs/msg/DiagnosticStatus: byte level, string name, message, hardware_id, KeyValue[] values
    level: byte
    name: str
    message: str
    hardware_id: str
    values: sequence[KeyValue]


@dataclass
class DiagnosticArray(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticArray_"):
    header: Header  # diagnostic_msgs/msg/DiagnosticArray: std_msgs/Header header, DiagnosticStatus[] status
    status: sequence[DiagnosticStatus]


@dataclass
class Empty(IdlStruct, typename="std_msgs::msg::dds_::Empty_"):
    structure_needs_at_least_one_member: uint8 = 0  # std_msgs/msg/Empty: no field; rosidl adds this one


@dataclass
class TriggerRequest(IdlStruct, typename="std_srvs::srv::dds_::Trigger_Request_"):
    guid: uint64  # rmw_cyclonedds's request header, then std_srvs/srv/Trigger's request (no field)
    seq: int64
    structure_needs_at_least_one_member: uint8 = 0


@dataclass
class TriggerResponse(IdlStruct, typename="std_srvs::srv::dds_::Trigger_Response_"):
    guid: uint64  # the request's header, then Trigger's response: bool success, string message
    seq: int64
    success: bool = False
    message: str = ""


@dataclass
class SampleStatus(IdlStruct, typename="ftsensord_msgs::msg::dds_::SampleStatus_"):
    header: Header  # ftsensord_msgs/msg/SampleStatus (docs/guide/clients.md, Recording): Header header,
    seq: uint64  # uint64 seq, uint32 flags, uint32 missed
    flags: uint32
    missed: uint32


@dataclass
class Gid(IdlStruct, typename="rmw_dds_common::msg::dds_::Gid_"):
    data: array[uint8, 16]  # rmw_dds_common/msg/Gid (Iron, Jazzy): char[16] data; one byte each on the wire


@dataclass
class NodeEntitiesInfo(IdlStruct, typename="rmw_dds_common::msg::dds_::NodeEntitiesInfo_"):
    node_namespace: bounded_str[256]  # rmw_dds_common/msg/NodeEntitiesInfo: string<=256 node_namespace,
    node_name: bounded_str[256]  # string<=256 node_name, Gid[] reader_gid_seq, Gid[] writer_gid_seq
    reader_gid_seq: sequence[Gid]
    writer_gid_seq: sequence[Gid]


@dataclass
class ParticipantEntitiesInfo(IdlStruct, typename="rmw_dds_common::msg::dds_::ParticipantEntitiesInfo_"):
    gid: Gid  # rmw_dds_common/msg/ParticipantEntitiesInfo: Gid gid, NodeEntitiesInfo[] node_entities_info_seq
    node_entities_info_seq: sequence[NodeEntitiesInfo]


TYPES = {
    "WrenchStamped": WrenchStamped,
    "SampleStatus": SampleStatus,
    "DiagnosticArray": DiagnosticArray,
    "QuaternionStamped": QuaternionStamped,
    "Imu": Imu,
    "Empty": Empty,
}


def qos(reliable: bool, user_data: str = "") -> Qos:
    """ROS 2's default profile (reliable, keep last 10) or SensorDataQoS (best effort, keep last 5)."""
    policies = [
        Policy.Reliability.Reliable(10**9) if reliable else Policy.Reliability.BestEffort,
        Policy.Durability.Volatile,
        Policy.History.KeepLast(10 if reliable else 5),
        Policy.DataRepresentation(use_cdrv0_representation=True),
    ]
    return Qos(*policies, *([Policy.Userdata(user_data.encode())] if user_data else []))


def wait_matched(entity, timeout_s: float = 10.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        status = (
            entity.get_publication_matched_status()
            if isinstance(entity, DataWriter)
            else entity.get_subscription_matched_status()
        )
        if status.current_count > 0:
            return True
        time.sleep(0.02)
    return False


def read(dp, step: dict) -> None:
    """``count`` messages of each topic, with the writer's type name and USER_DATA as discovered."""
    readers = {
        t: DataReader(dp, Topic(dp, t, TYPES[kind]), qos(step["reliable"]))
        for t, kind in step["topics"].items()
    }
    publications = BuiltinDataReader(dp, BuiltinTopicDcpsPublication)
    got: dict[str, list] = {t: [] for t in readers}
    end = time.monotonic() + step.get("timeout_s", 20.0)
    while time.monotonic() < end and any(len(v) < step["count"] for v in got.values()):
        for t, r in readers.items():
            for m in r.take(N=100):
                if len(got[t]) < step["count"]:
                    got[t].append({**asdict(m), "received": time.time()})
        time.sleep(0.002)
    seen = {}
    for p in publications.take(N=1000):
        if p.topic_name in readers:
            seen[p.topic_name] = {
                "type_name": p.type_name,
                "user_data": p.qos[Policy.Userdata].data.decode() if Policy.Userdata in p.qos else "",
            }
    for t, msgs in got.items():
        print(json.dumps({"topic": t, "writer": seen.get(t), "messages": msgs}), flush=True)


def nodes(dp, step: dict) -> None:
    """The graph as rmw_cyclonedds reads it: ``ros_discovery_info`` (reliable, transient-local,
    keep all: rmw_node.cpp), each participant's nodes with their endpoints' GIDs, beside the
    GUIDs of the endpoints discovered on ``topics`` and of the participants that have them."""
    qos = Qos(
        Policy.Reliability.Reliable(10**9),
        Policy.Durability.TransientLocal,
        Policy.History.KeepAll,
        Policy.DataRepresentation(use_cdrv0_representation=True),
    )
    reader = DataReader(dp, Topic(dp, "ros_discovery_info", ParticipantEntitiesInfo), qos)
    publications = BuiltinDataReader(dp, BuiltinTopicDcpsPublication)
    subscriptions = BuiltinDataReader(dp, BuiltinTopicDcpsSubscription)
    infos, endpoints = {}, {}
    end = time.monotonic() + step.get("timeout_s", 20.0)
    while time.monotonic() < end and not (infos and set(step["topics"]) <= set(endpoints)):
        for m in reader.take(N=100):
            infos[bytes(m.gid.data).hex()] = [
                {
                    "namespace": n.node_namespace,
                    "name": n.node_name,
                    "readers": [bytes(g.data).hex() for g in n.reader_gid_seq],
                    "writers": [bytes(g.data).hex() for g in n.writer_gid_seq],
                }
                for n in m.node_entities_info_seq
            ]
        for e in [*publications.take(N=1000), *subscriptions.take(N=1000)]:
            if e.topic_name in step["topics"]:
                endpoints.setdefault(e.topic_name, []).append(
                    {"guid": e.key.bytes.hex(), "participant": e.participant_key.bytes.hex()}
                )
        time.sleep(0.05)
    print(json.dumps({"participants": infos, "endpoints": endpoints}), flush=True)


def publish(dp, step: dict) -> None:
    """``message`` (its fields as JSON) on ``topic``, ``times`` times ``period_s`` apart, once matched."""
    cls = TYPES[step["type"]]
    writer = DataWriter(dp, Topic(dp, step["topic"], cls), qos(step.get("reliable", True)))
    matched = wait_matched(writer)
    m = step["message"]
    msg = (
        cls(**m)
        if step["type"] == "Empty"
        else cls(
            Header(Time(*m["stamp"]), m.get("frame_id", "")),
            Quaternion(*m["q_xyzw"]),
            *(
                [[0.0] * 9, Vector3(0, 0, 0), [0.0] * 9, Vector3(0, 0, 0), [0.0] * 9]
                if step["type"] == "Imu"
                else []
            ),
        )
    )
    if step["type"] == "Imu":
        msg.orientation_covariance = [m.get("covariance0", 0.0)] + [0.0] * 8
    for _ in range(step.get("times", 1)):
        writer.write(msg)
        time.sleep(step.get("period_s", 0.0))
    print(json.dumps({"published": step["topic"], "matched": matched}), flush=True)


def orient(dp, topics: list, stop: threading.Event, ready: threading.Event) -> None:
    """The identity orientation on each of ``topics`` at 100 Hz until ``stop``; ``ready`` set once
    every writer is matched and has written (a loaded host's discovery takes more than 0.2 s)."""
    writers = [DataWriter(dp, Topic(dp, t, QuaternionStamped), qos(False)) for t in topics]
    for w in writers:
        wait_matched(w)
    while not stop.is_set():
        now = time.time()
        for w in writers:
            w.write(QuaternionStamped(Header(Time(int(now), int(now % 1 * 1e9)), ""), Quaternion(0, 0, 0, 1)))
        ready.set()
        time.sleep(0.01)


def oriented(dp, topics: list, stop: threading.Event) -> None:
    """`orient` in a thread of its own; returns once its orientations are coming."""
    ready = threading.Event()
    threading.Thread(target=orient, args=(dp, topics, stop, ready), daemon=True).start()
    ready.wait(10.0)
    time.sleep(0.1)  # a few more in, the daemon's newest fresh


def call_trigger(dp, step: dict) -> None:
    """std_srvs/srv/Trigger on service ``name`` as rmw_cyclonedds's client calls it."""
    clientid = "clientid=" + ".".join(f"{b:x}" for b in dp.guid.bytes) + ";"
    writer = DataWriter(dp, Topic(dp, f"rq{step['name']}Request", TriggerRequest), qos(True, clientid))
    reader = DataReader(dp, Topic(dp, f"rr{step['name']}Reply", TriggerResponse), qos(True, clientid))
    available = wait_matched(writer) and wait_matched(reader)
    keep = threading.Event()
    if step.get(
        "orient"
    ):  # orientations kept coming during the call, as a tare under gravity compensation needs
        oriented(dp, step["orient"], keep)
    guid = writer.get_instance_handle() & (
        2**64 - 1
    )  # rmw_send_request: header.guid = the writer's instance handle
    seqs = list(range(7, 7 + step.get("requests", 1)))  # back to back, as several callers would
    for seq in seqs:
        writer.write(TriggerRequest(guid, seq))
    replies = []
    end = time.monotonic() + step.get("timeout_s", 20.0)
    while time.monotonic() < end and len(replies) < len(seqs):
        replies += [r for r in reader.take(N=10) if r.guid == guid]  # rmw_take_response: only this client's
        time.sleep(0.01)
    keep.set()
    for r in sorted(replies, key=lambda r: r.seq):
        print(
            json.dumps({"service": step["name"], "available": available, **asdict(r), "sent_guid": guid}),
            flush=True,
        )


def tare_topic(dp, step: dict) -> None:
    """std_msgs/msg/Empty on ``topic``, orientations coming meanwhile, until /diagnostics says
    every sensor is tared (the tare takes 100 samples: 1 s at 100 Hz, more on a loaded host;
    a fixed wait of 3 s was too short at times) or ``timeout_s`` passed."""
    writer = DataWriter(dp, Topic(dp, step["topic"], Empty), qos(True))
    diagnostics = DataReader(dp, Topic(dp, "rt/diagnostics", DiagnosticArray), qos(True))
    matched = wait_matched(writer)
    keep = threading.Event()
    oriented(dp, step["orient"], keep)  # the orientations in before the tare's first sample
    writer.write(Empty())
    tared, end = False, time.monotonic() + step.get("timeout_s", 20.0)
    while not tared and time.monotonic() < end:
        time.sleep(0.05)
        for m in diagnostics.take(N=16):  # a sensor's status has a "tared" value, the others none
            said = [kv.value for s in m.status for kv in s.values if kv.key == "tared"]
            tared = bool(said) and all(v == "True" for v in said)
    keep.set()
    print(json.dumps({"published": step["topic"], "matched": matched, "tared": tared}), flush=True)


def main() -> int:
    dp = DomainParticipant(int(sys.argv[1]))
    for step in json.loads(sys.argv[2]):
        {
            "read": read,
            "nodes": nodes,
            "publish": publish,
            "trigger": call_trigger,
            "trigger-topic": tare_topic,
        }[step["do"]](dp, step)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
