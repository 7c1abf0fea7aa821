"""The DDS participant that is ftsensord's ROS 2 node: its writers, readers and the tare service.

Topics (ROS names; the DDS topic is ``rt`` + the name):

- ``/<ns>/wrench/<stream>`` (``wrench/sensor1``, ``wrench/tip``, ``wrench/tip/compensated``...):
  ``geometry_msgs/msg/WrenchStamped``, N and Nm, stamp the sample's ``t_wall``, frame_id its frame;
  ``/<ns>/wrench/<stream>/status``: ``ftsensord_msgs/msg/SampleStatus`` (seq, flags, missed);
  ``/<ns>/wrench/<stream>/sigma`` (a sensor's, the tip's and their compensated ones, `wire.has_sigma`):
  ``geometry_msgs/msg/WrenchStamped``, the same sample's 1-sigma per axis (N, Nm; NaN
  unknown), its stamp and frame_id (docs/guide/ros2.md says why a companion of this type);
- ``/diagnostics``: ``diagnostic_msgs/msg/DiagnosticArray``, about 1 Hz;
- in: ``/<ns>/orientation/<frame>`` (``geometry_msgs/msg/QuaternionStamped``) and ``/<ns>/imu/<frame>``
  (``sensor_msgs/msg/Imu``, its orientation), R_world,frame for gravity compensation;
- in: ``/<ns>/tare`` (``std_msgs/msg/Empty``: any rmw), and the service ``/<ns>/tare``
  (``std_srvs/srv/Trigger``, as rmw_cyclonedds carries services: `msgs`).

QoS of every writer: reliable, volatile, keep last 10 (ROS's default publisher profile),
so a default subscriber (reliable) and a ``SensorDataQoS`` one (best effort) both match;
USER_DATA ``typehash=RIHS01_...;`` (REP 2011); plain CDR (XCDR1), as the rmws read it.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable
from typing import Any

# ddspy_write: the C call DataWriter.write ends in, given the CDR bytes (the extra pins the
# binding's major version for it; tests/test_ros2.py checks the bytes against its serializer).
from cyclonedds._clayer import ddspy_write
from cyclonedds.core import (
    DDSException,
    InstanceState,
    Policy,
    Qos,
    ReadCondition,
    SampleState,
    ViewState,
    WaitSet,
)
from cyclonedds.domain import Domain, DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic

from ftsensord.protocol import wire
from ftsensord.recording.ros2mcap import Stamped, missed_since, status_body
from ftsensord.ros2 import diagnostics, msgs
from ftsensord.ros2.diagnostics import Status

log = logging.getLogger("ftsensord.ros2")

#: ROS 2's default publisher depth ("keep last 10"): what `ros2 topic echo` and rclcpp assume.
DEPTH = 10
#: The node's name; its namespace is the topics' (``ros2 node list``: /<namespace>/ftsensord).
NODE_NAME = "ftsensord"
#: The participant's USER_DATA as rmw_cyclonedds sets it (rmw_node.cpp, rmw_context_impl_s::init:
#: ``"enclave=" + enclave + ";"``); ROS's graph takes a participant with it for a ROS one.
ENCLAVE = b"enclave=/;"
#: How long a tare reply waits for the client's reply reader to be matched (rmw_cyclonedds's own
#: rmw_send_response waits 100 ms; a tare takes a second, so this is rarely spent).
REPLY_MATCH_S = 1.0


#: Added to the user's CYCLONEDDS_URI for the node's domain: Fast DDS's (vendor 1.15) XTypes
#: type information ignored, so its endpoints match on the type's name, as ROS 2's own rmws
#: match (with REP 2011's type hash in USER_DATA). Fast DDS 3 (Kilted and later) advertises
#: type identifiers that differ from the binding's for a sequence of structs
#: (DiagnosticArray's statuses, ros_discovery_info's nodes): Cyclone must then resolve the
#: remote type before it matches, and never does (its type lookup returns a complete type
#: object whose collection element flags Cyclone's validation rejects, "invalid type
#: object", and never the minimal one it asked for): such a reader was never matched.
FAST_DDS_TYPES_IGNORED = (
    "<CycloneDDS><Domain Id='any'><Compatibility>"
    "<IgnoreTypeInformation>1.15</IgnoreTypeInformation>"
    "</Compatibility></Domain></CycloneDDS>"
)
#: The domains made here, by id: kept for the process's life (deleting a Domain deletes every
#: participant in it, another node's too).
_domains: dict[int, Domain] = {}


def domain_config() -> str:
    """The node's domain configuration: the user's CYCLONEDDS_URI (files or XML, in the order
    Cyclone reads them), then `FAST_DDS_TYPES_IGNORED`, which overrides theirs on that setting."""
    user = os.environ.get("CYCLONEDDS_URI", "").strip()
    return f"{user},{FAST_DDS_TYPES_IGNORED}" if user else FAST_DDS_TYPES_IGNORED


def join_domain(domain_id: int) -> None:
    """Domain ``domain_id`` made with `domain_config`, once a process; a domain this process
    already has (a participant of the binding's made before, without this) is left as it is."""
    if domain_id not in _domains:
        try:
            _domains[domain_id] = Domain(domain_id, domain_config())
        except DDSException as exc:
            if exc.code != DDSException.DDS_RETCODE_PRECONDITION_NOT_MET:  # it exists already
                raise


def writer_qos(cls: type, extra: str = "", latched: bool = False) -> Qos:
    """Reliable, volatile, keep last 10, XCDR1; USER_DATA ``<extra>typehash=RIHS01_...;``.
    ``latched``: transient-local, keep last 1 (``ros_discovery_info``'s, as the rmw's)."""
    durability = Policy.Durability.TransientLocal if latched else Policy.Durability.Volatile
    return Qos(
        Policy.Reliability.Reliable(0),
        durability,
        Policy.History.KeepLast(1 if latched else DEPTH),
        Policy.DataRepresentation(use_cdrv0_representation=True),
        Policy.Userdata(f"{extra}typehash={msgs.type_hash(cls)};".encode()),
    )


def reader_qos(cls: type, reliable: bool, extra: str = "") -> Qos:
    """A reader's QoS: best effort matches every writer; reliable (a command) only reliable ones."""
    reliability = Policy.Reliability.Reliable(0) if reliable else Policy.Reliability.BestEffort
    return Qos(
        reliability,
        Policy.Durability.Volatile,
        Policy.History.KeepLast(DEPTH if reliable else 1),
        Policy.DataRepresentation(use_cdrv0_representation=True),
        Policy.Userdata(f"{extra}typehash={msgs.type_hash(cls)};".encode()),
    )


class Ros2Node:
    """ftsensord on a DDS domain: `publish` a sample, `publish_diagnostics`; `serve` (a thread)
    reads the inputs and calls ``on_orientation(frame, q_xyzw, t)`` and ``on_tare() -> (ok, text)``."""

    def __init__(self, namespace: str, domain_id: int, frames: dict[str, str], orientation_frames: list[str]):
        self.namespace, self.frames = namespace, frames
        join_domain(domain_id)
        self.participant = DomainParticipant(domain_id, qos=Qos(Policy.Userdata(ENCLAVE)))
        self.writers: dict[str, tuple[DataWriter, DataWriter, Stamped]] = {}
        self.sigma_writers: dict[str, DataWriter] = {}  # a stream's sigma companion (`wire.has_sigma`)
        self.last_seq: dict[str, int] = {}
        self.write_errors = 0
        # The sample writers some reader matches (`find_readers`): a sample on a topic nobody
        # reads is not written (a volatile writer keeps nothing for a later reader), so the
        # bridge's CPU is its subscribed topics', not every stream's.
        self.read: set[DataWriter] = set()
        for stream in frames:
            self._writers(stream)
        self.diagnostics = self._writer("rt/diagnostics", msgs.DiagnosticArray)
        ns = f"/{namespace}"
        self.inputs: list[tuple[DataReader, str, str]] = []  # reader, kind, frame
        for frame in orientation_frames:
            self.inputs.append(
                (self._reader(f"rt{ns}/orientation/{frame}", msgs.QuaternionStamped), "quat", frame)
            )
            self.inputs.append((self._reader(f"rt{ns}/imu/{frame}", msgs.Imu), "imu", frame))
        self.inputs.append((self._reader(f"rt{ns}/tare", msgs.Empty, reliable=True), "tare", ""))
        # rmw_cyclonedds pairs a service's reader and writer by this id (check_for_service_reader_writer).
        serviceid = "serviceid=" + ".".join(f"{b:x}" for b in self.participant.guid.bytes) + ";"
        self.requests = DataReader(
            self.participant,
            Topic(self.participant, f"rq{ns}/tareRequest", msgs.TriggerRequestWire),
            reader_qos(msgs.TriggerRequest, True, serviceid),
        )
        self.replies = DataWriter(
            self.participant,
            Topic(self.participant, f"rr{ns}/tareReply", msgs.TriggerResponseWire),
            writer_qos(msgs.TriggerResponse, serviceid),
        )
        self.inputs.append((self.requests, "service", ""))
        self.waitset = WaitSet(self.participant)
        for reader, _, _ in self.inputs:
            self.waitset.attach(ReadCondition(reader, SampleState.Any | ViewState.Any | InstanceState.Any))
        self.received: dict[str, int] = {"orientation": 0, "imu_without_orientation": 0, "tare": 0}
        self.taring = threading.Lock()
        self.discovery = DataWriter(
            self.participant,
            Topic(self.participant, "ros_discovery_info", msgs.ParticipantEntitiesInfo),
            writer_qos(msgs.ParticipantEntitiesInfo, latched=True),
        )
        self.announce()

    def announce(self) -> None:
        """The node on ``ros_discovery_info``, as every rmw says which nodes a participant has:
        ``rmw_dds_common/msg/ParticipantEntitiesInfo``, the participant's GID and, for the node,
        its name, namespace and its readers' and writers' GIDs (rmw_cyclonedds_cpp's
        convert_guid_to_gid: a GID is the entity's 16-byte DDS GUID, rmw_node.cpp). The topic
        name is not prefixed (avoid_ros_namespace_conventions); reliable, transient-local, keep
        last 1: a node that starts later still reads it. Written again when a stream's writers
        are made later. Iron and later (their Gid is 16 bytes; Humble's 24)."""

        def gid(entity: Any) -> msgs.Gid:
            return msgs.Gid(list(entity.get_guid().bytes))

        writers = [w for ws in self.writers.values() for w in ws[:2]] + [*self.sigma_writers.values()]
        writers += [self.diagnostics, self.replies]
        node = msgs.NodeEntitiesInfo(
            "/" + self.namespace, NODE_NAME, [gid(r) for r, _, _ in self.inputs], [gid(w) for w in writers]
        )
        self.discovery.write(msgs.ParticipantEntitiesInfo(gid(self.participant), [node]))

    def _writer(self, topic: str, cls: type) -> DataWriter:
        return DataWriter(self.participant, Topic(self.participant, topic, cls), writer_qos(cls))

    def find_readers(self) -> None:
        """Which sample writers a reader matches now. Asked (the bridge: five times a second),
        not told by a matched listener: Cyclone runs a listener in its own thread, which
        then waits for the GIL, and deleting an entity waits for its listeners."""
        self.read = {
            w
            for w in [*(w for ws in self.writers.values() for w in ws[:2]), *self.sigma_writers.values()]
            if w.get_publication_matched_status().current_count > 0
        }

    def _reader(self, topic: str, cls: type, reliable: bool = False) -> DataReader:
        return DataReader(self.participant, Topic(self.participant, topic, cls), reader_qos(cls, reliable))

    def _writers(self, stream: str) -> tuple[DataWriter, DataWriter, Stamped]:
        if stream not in self.writers:
            topic = f"rt/{self.namespace}/{stream}"
            self.writers[stream] = (
                self._writer(topic, msgs.WrenchStamped),
                self._writer(topic + "/status", msgs.SampleStatus),
                Stamped(self.frames.get(stream, stream)),
            )
            if wire.has_sigma(stream):
                self.sigma_writers[stream] = self._writer(topic + "/sigma", msgs.WrenchStamped)
            if hasattr(self, "discovery"):  # a stream the daemon's status did not have at start
                self.announce()
        return self.writers[stream]

    # A sample's messages are written as CDR bytes made by `Stamped` (the wrench's values are
    # the wire's own float64 bytes): IdlStruct objects and their Python serializer cost about
    # 0.15 ms a message on a cold cache, `struct` a tenth (docs/design/performance.md, "The ROS 2 output").
    def publish_wrench(self, topic: str, t_wall: float, values: bytes) -> None:
        """A wrench sample of stream ``topic`` as its WrenchStamped: ``values`` fx fy fz mx my mz
        (N, Nm; 48 bytes, little-endian float64 as on the wire), stamped ``t_wall`` (UNIX s)."""
        writer, _, cdr = self._writers(topic)
        if writer in self.read:
            self._write(writer, cdr.message(t_wall, values))

    def publish_sigma(self, topic: str, t_wall: float, values: bytes) -> None:
        """A wrench sample's sigma on ``<topic>/sigma`` as a WrenchStamped: ``values`` the 1-sigma
        of fx fy fz mx my mz (N, Nm; NaN unknown; 48 bytes as on the wire), stamped and framed
        as its wrench."""
        writer = self.sigma_writers.get(topic)
        if writer is not None and writer in self.read:
            self._write(writer, self._writers(topic)[2].message(t_wall, values))

    def publish_status(self, topic: str, t_wall: float, seq: int, flags: int) -> None:
        """A wrench sample's SampleStatus: seq, flags, seqs missed since the stream's previous."""
        last = self.last_seq.get(topic)
        self.last_seq[topic] = seq
        _, writer, cdr = self._writers(topic)
        if writer in self.read:
            self._write(writer, cdr.message(t_wall, status_body(seq, flags, missed_since(last, seq))))

    def _write(self, writer: DataWriter, cdr: bytes) -> None:
        if ddspy_write(writer._ref, cdr) < 0:  # noqa: SLF001 (the writer's handle, as DataWriter.write passes it)
            self.write_errors += 1  # counted, said at exit: the next sample is the newer one anyway

    def publish_diagnostics(self, statuses: list[Status], t_wall: float) -> None:
        self.write_diagnostics(diagnostics.cdr(statuses, t_wall))

    def write_diagnostics(self, cdr: bytes) -> None:
        """A DiagnosticArray's CDR bytes (`diagnostics.Encoder`'s message) on /diagnostics."""
        self._write(self.diagnostics, cdr)

    def serve(
        self,
        timeout_s: float,
        on_orientation: Callable[[str, list[float], float], None],
        on_tare: Callable[[], tuple[bool, str]],
    ) -> None:
        """Wait for input up to ``timeout_s`` and handle what came: orientations at once,
        each tare in a thread of its own (it takes the tare's samples to answer). ``timeout_s`` 0:
        asked without waiting (the in-loop output, each cycle: about a microsecond when nothing came)."""
        if not self.waitset.wait(int(timeout_s * 1e9)):
            return
        for reader, kind, frame in self.inputs:
            for msg in reader.take(N=64):
                if not msg.sample_info.valid_data:
                    continue  # a writer gone (unregistered, disposed): no message
                try:
                    self._handle(reader, kind, frame, msg, on_orientation, on_tare)
                except (DDSException, ValueError, TypeError) as exc:
                    log.warning("%s input on %s dropped: %s", kind, reader.topic.name, exc)

    def _handle(
        self,
        reader: DataReader,
        kind: str,
        frame: str,
        msg: Any,
        on_orientation: Callable[[str, list[float], float], None],
        on_tare: Callable[[], tuple[bool, str]],
    ) -> None:
        if kind in ("quat", "imu"):
            q = msg.quaternion if kind == "quat" else msg.orientation
            # sensor_msgs/Imu: orientation_covariance[0] = -1 says the IMU gives no orientation.
            if kind == "imu" and msg.orientation_covariance[0] == -1:
                self.received["imu_without_orientation"] += 1
                return
            self.received["orientation"] += 1
            on_orientation(
                frame, [q.x, q.y, q.z, q.w], msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
            )
        else:
            self.received["tare"] += 1
            clientid = (
                None
                if kind == "tare"
                else self._clientid(reader.get_matched_publication_data(msg.sample_info.publication_handle))
            )
            reply = None if kind == "tare" else (msg.guid, msg.seq, clientid)
            # One tare at a time (the daemon refuses a second anyway): a flood of requests
            # is answered at once, never a thread each.
            if not self.taring.acquire(blocking=False):
                if reply is not None:
                    self._reply(*reply, False, "a tare from ROS is under way: try again when it is done")
                return
            threading.Thread(target=self._tare, args=(reply, on_tare), daemon=True).start()

    @staticmethod
    def _clientid(endpoint: Any) -> str | None:
        """The ``clientid=`` of an rmw_cyclonedds endpoint's USER_DATA (None: none given)."""
        qos = endpoint.qos if endpoint is not None else {}
        data = qos[Policy.Userdata].data.decode(errors="replace") if Policy.Userdata in qos else ""
        found = [part.split("=", 1)[1] for part in data.split(";") if part.startswith("clientid=")]
        return found[0] if found else None

    def _tare(
        self, reply: tuple[int, int, str | None] | None, on_tare: Callable[[], tuple[bool, str]]
    ) -> None:
        try:
            ok, text = on_tare()
        finally:
            self.taring.release()
        if reply is not None:
            self._reply(*reply, ok, text)

    def _reply(self, guid: int, seq: int, clientid: str | None, ok: bool, text: str) -> None:
        """The service's response, once the client's reply reader is matched (as rmw_send_response)."""
        if clientid is not None:
            end = time.monotonic() + REPLY_MATCH_S
            while time.monotonic() < end and not any(
                self._clientid(self.replies.get_matched_subscription_data(h)) == clientid
                for h in self.replies.get_matched_subscriptions()
            ):
                time.sleep(0.01)
        self.replies.write(msgs.TriggerResponseWire(guid, seq, ok, text))
