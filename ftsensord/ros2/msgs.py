"""The ROS 2 message types the bridge speaks, as DDS types, and their RIHS01 type hashes.

Each class is the DDS type a ROS 2 rmw registers for the message: type name
``<pkg>::msg::dds_::<Type>_``, members in the .msg file's order, plain CDR (XCDR1,
little-endian) on the wire, as rmw_cyclonedds writes it (its ``create_sertype`` allows
XCDR1 only). A message without fields carries ``uint8 structure_needs_at_least_one_member``,
as rosidl generates it.

A service over rmw_cyclonedds is two topics, ``rq/<name>Request`` and ``rr/<name>Reply``,
whose samples start with the request header ``{uint64 guid; int64 seq}``, then the request's
or the response's members (rmw_cyclonedds_cpp/src/serdata.hpp, ``cdds_request_header_t``;
serdata.cpp serialises it as a prefix): the ``*Wire`` types below. Other rmws (Fast DDS,
Connext) carry the request id differently; their clients do not match these.

`type_hash` computes the RIHS01 hash of REP 2011 from these same classes: the type
description (the type and every type it refers to, each field's type id, capacity, string
capacity and nested type name), serialised as rosidl_generator_type_description serialises it
(json.dumps, ``separators=(", ", ": ")``, default values left out), then SHA-256.
"""

# No `from __future__ import annotations`: cyclonedds resolves the fields' annotations itself
# and cannot resolve a builtin (str) given as a string.
import hashlib
import json
import typing
from dataclasses import dataclass, field, fields

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


def _ros_name(cls: type) -> str:
    """``geometry_msgs::msg::dds_::Vector3_`` -> ``geometry_msgs/msg/Vector3``."""
    return cls.__idl_typename__.replace("::dds_::", "::").rstrip("_").replace("::", "/")  # type: ignore[attr-defined]


@dataclass
class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: int32 = 0
    nanosec: uint32 = 0


@dataclass
class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time = field(default_factory=Time)
    frame_id: str = ""


@dataclass
class Vector3(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0


@dataclass
class Wrench(IdlStruct, typename="geometry_msgs::msg::dds_::Wrench_"):
    force: Vector3 = field(default_factory=Vector3)
    torque: Vector3 = field(default_factory=Vector3)


@dataclass
class WrenchStamped(IdlStruct, typename="geometry_msgs::msg::dds_::WrenchStamped_"):
    header: Header = field(default_factory=Header)
    wrench: Wrench = field(default_factory=Wrench)


@dataclass
class Quaternion(IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0
    w: float64 = 1.0


@dataclass
class QuaternionStamped(IdlStruct, typename="geometry_msgs::msg::dds_::QuaternionStamped_"):
    header: Header = field(default_factory=Header)
    quaternion: Quaternion = field(default_factory=Quaternion)


@dataclass
class Imu(IdlStruct, typename="sensor_msgs::msg::dds_::Imu_"):
    header: Header = field(default_factory=Header)
    orientation: Quaternion = field(default_factory=Quaternion)
    orientation_covariance: array[float64, 9] = field(default_factory=lambda: [0.0] * 9)
    angular_velocity: Vector3 = field(default_factory=Vector3)
    angular_velocity_covariance: array[float64, 9] = field(default_factory=lambda: [0.0] * 9)
    linear_acceleration: Vector3 = field(default_factory=Vector3)
    linear_acceleration_covariance: array[float64, 9] = field(default_factory=lambda: [0.0] * 9)


@dataclass
class KeyValue(IdlStruct, typename="diagnostic_msgs::msg::dds_::KeyValue_"):
    key: str = ""
    value: str = ""


@dataclass
class DiagnosticStatus(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticStatus_"):
    level: byte = 0  # OK 0, WARN 1, ERROR 2, STALE 3
    name: str = ""
    message: str = ""
    hardware_id: str = ""
    values: sequence[KeyValue] = field(default_factory=list)


@dataclass
class DiagnosticArray(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticArray_"):
    header: Header = field(default_factory=Header)
    status: sequence[DiagnosticStatus] = field(default_factory=list)


@dataclass
class Empty(IdlStruct, typename="std_msgs::msg::dds_::Empty_"):
    structure_needs_at_least_one_member: uint8 = 0


@dataclass
class TriggerRequest(IdlStruct, typename="std_srvs::srv::dds_::Trigger_Request_"):
    structure_needs_at_least_one_member: uint8 = 0


@dataclass
class TriggerResponse(IdlStruct, typename="std_srvs::srv::dds_::Trigger_Response_"):
    success: bool = False
    message: str = ""


@dataclass
class TriggerRequestWire(IdlStruct, typename="std_srvs::srv::dds_::Trigger_Request_"):
    """A Trigger request as rmw_cyclonedds sends it: the request header, then the request."""

    guid: uint64 = 0
    seq: int64 = 0
    structure_needs_at_least_one_member: uint8 = 0


@dataclass
class TriggerResponseWire(IdlStruct, typename="std_srvs::srv::dds_::Trigger_Response_"):
    """A Trigger response as rmw_cyclonedds sends it: the request's header, then the response."""

    guid: uint64 = 0
    seq: int64 = 0
    success: bool = False
    message: str = ""


#: type_description_interfaces/msg/FieldType's ids of the primitive types used here.
_TYPE_IDS = {
    "int8": 2,
    "uint8": 3,
    "int16": 4,
    "uint16": 5,
    "int32": 6,
    "uint32": 7,
    "int64": 8,
    "uint64": 9,
    "float32": 10,
    "float64": 11,
    "char": 13,
    "bool": 15,
    "byte": 16,
    "str": 17,
}
_BOUNDED_STRING = 21
_NESTED = 1
#: FieldType adds these to a type id for a fixed array, a bounded and an unbounded sequence.
_ARRAY, _BOUNDED, _UNBOUNDED = 48, 96, 144


def _field_type(hint: object, ros_type: str | None = None) -> tuple[dict[str, object], type | None]:
    """A field's FieldType (as a dict) and the nested class it names, if any; ``ros_type``: the
    .msg's primitive where the class's differs (`Gid`)."""
    capacity, offset = 0, 0
    args = typing.get_args(hint)
    if args and hasattr(args[1], "subtype"):  # array[...] or sequence[...]
        holder = args[1]
        length = getattr(holder, "length", None)
        if length is not None:
            capacity, offset = length, _ARRAY
        else:
            bound = getattr(holder, "max_length", None)
            capacity, offset = (bound, _BOUNDED) if bound else (0, _UNBOUNDED)
        hint = holder.subtype
        args = typing.get_args(hint)
    if isinstance(hint, type) and issubclass(hint, IdlStruct):
        return (
            {
                "type_id": _NESTED + offset,
                "capacity": capacity,
                "string_capacity": 0,
                "nested_type_name": _ros_name(hint),
            },
            hint,
        )
    if args and isinstance(args[1], bounded_str):  # string<=N
        return {
            "type_id": _BOUNDED_STRING + offset,
            "capacity": capacity,
            "string_capacity": args[1].max_length,
            "nested_type_name": "",
        }, None
    name = ros_type or (args[1] if args else hint.__name__)  # type: ignore[attr-defined]
    return {
        "type_id": _TYPE_IDS[name] + offset,
        "capacity": capacity,
        "string_capacity": 0,
        "nested_type_name": "",
    }, None


def _describe(cls: type) -> tuple[dict[str, object], list[type]]:
    hints = typing.get_type_hints(cls, include_extras=True)
    out, nested = [], []
    for f in fields(cls):
        ftype, inner = _field_type(hints[f.name], getattr(cls, "ROS_TYPES", {}).get(f.name))
        out.append({"name": f.name, "type": ftype})
        if inner is not None:
            nested.append(inner)
    return {"type_name": _ros_name(cls), "fields": out}, nested


def type_description(cls: type) -> dict[str, object]:
    """REP 2011's TypeDescription of ``cls``, default values left out (they are not hashed)."""
    main, todo = _describe(cls)
    seen: dict[str, dict[str, object]] = {}
    while todo:
        inner = todo.pop()
        name = _ros_name(inner)
        if name not in seen:
            seen[name], more = _describe(inner)
            todo += more
    return {"type_description": main, "referenced_type_descriptions": [seen[k] for k in sorted(seen)]}


def type_hash(cls: type) -> str:
    """``RIHS01_<sha256 hex>`` of ``cls``'s type description (REP 2011)."""
    text = json.dumps(type_description(cls), ensure_ascii=True, allow_nan=False, separators=(", ", ": "))
    return "RIHS01_" + hashlib.sha256(text.encode()).hexdigest()


@dataclass
class SampleStatus(IdlStruct, typename="ftsensord_msgs::msg::dds_::SampleStatus_"):
    """One sample's bookkeeping, as in MCAP recordings (`recording.ros2mcap.SCHEMAS`)."""

    header: Header = field(default_factory=Header)
    seq: uint64 = 0
    flags: uint32 = 0
    missed: uint32 = 0


@dataclass
class Gid(IdlStruct, typename="rmw_dds_common::msg::dds_::Gid_"):
    """rmw_dds_common/msg/Gid since Iron: ``char[16] data``, a DDS GUID's 16 bytes (Humble's is
    char[24]). A char is one byte on the wire; uint8 here (the binding's char takes 0-127 only),
    hashed as the .msg's char."""

    ROS_TYPES = {"data": "char"}  # not annotated: a class attribute, no IDL member
    data: array[uint8, 16] = field(default_factory=lambda: [0] * 16)


@dataclass
class NodeEntitiesInfo(IdlStruct, typename="rmw_dds_common::msg::dds_::NodeEntitiesInfo_"):
    node_namespace: bounded_str[256] = "/"
    node_name: bounded_str[256] = ""
    reader_gid_seq: sequence[Gid] = field(default_factory=list)
    writer_gid_seq: sequence[Gid] = field(default_factory=list)


@dataclass
class ParticipantEntitiesInfo(IdlStruct, typename="rmw_dds_common::msg::dds_::ParticipantEntitiesInfo_"):
    """What every ROS 2 participant says on ``ros_discovery_info``: its GID and its nodes'
    names and endpoints' GIDs (how ``ros2 node list`` finds nodes)."""

    gid: Gid = field(default_factory=Gid)
    node_entities_info_seq: sequence[NodeEntitiesInfo] = field(default_factory=list)
