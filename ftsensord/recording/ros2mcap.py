"""Samples as ROS 2 messages in an MCAP file, written as they arrive.

Topics (a stream ``wrench/sensor1`` becomes ``/wrench/sensor1``):

- ``/wrench/<name>``: ``geometry_msgs/msg/WrenchStamped``, N and Nm, ``header.stamp``
  the sample's ``t_wall`` (UTC), ``header.frame_id`` the stream's frame.
- ``/wrench/<name>/sigma``: ``geometry_msgs/msg/WrenchStamped``, the same sample's 1-sigma
  per axis (force N, torque Nm; NaN: unknown or not received), stamped and framed as it.
- ``/flux/<sensor>/chip<i>``: ``sensor_msgs/msg/MagneticField`` per chip, T in the
  chip's frame (``<sensor>/chip<i>``), covariance all zero (ROS: unknown); NaN for a
  chip that did not answer, as on the wire.
- ``/<stream>/status``: ``ftsensord_msgs/msg/SampleStatus``, the sample's sequence
  number, flags (``ftsensord.protocol.wire``) and sequence numbers missed before it,
  stamped as the sample.

Messages are CDR (little-endian), encoded here for these fixed layouts; each
message's MCAP ``log_time`` and ``publish_time`` are its stamp, so viewers put it
at the sample's own time. ``mcap`` (the writer) is imported only here: the
``record`` extra.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from ftsensord import __version__
from ftsensord.errors import ConfigError
from ftsensord.protocol import wire

_SEP = "\n" + "=" * 80 + "\n"
_TIME = "MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec"
_HEADER = "MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id"
_VECTOR3 = "MSG: geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z"

#: ROS 2 message definitions as rosbag2 stores them: the type, then each dependency.
SCHEMAS = {
    "geometry_msgs/msg/WrenchStamped": _SEP.join(
        [
            "std_msgs/Header header\ngeometry_msgs/Wrench wrench",
            "MSG: geometry_msgs/Wrench\ngeometry_msgs/Vector3 force\ngeometry_msgs/Vector3 torque",
            _VECTOR3,
            _HEADER,
            _TIME,
        ]
    ),
    "sensor_msgs/msg/MagneticField": _SEP.join(
        [
            "std_msgs/Header header\ngeometry_msgs/Vector3 magnetic_field\nfloat64[9] magnetic_field_covariance",
            _VECTOR3,
            _HEADER,
            _TIME,
        ]
    ),
    "ftsensord_msgs/msg/SampleStatus": _SEP.join(
        [
            (
                "# One ftsensord sample's bookkeeping (ftsensord.protocol.wire).\n"
                "std_msgs/Header header\n"
                "uint64 seq     # the stream's sequence number: it counts the daemon's cycles\n"
                "uint32 flags   # FLAG_* bits: chip_missing 1, saturated 2, stale 4, overload 8, degraded 16, ...\n"
                "uint32 missed  # sequence numbers not received between the previous sample and this one"
            ),
            _HEADER,
            _TIME,
        ]
    ),
}
WRENCH, FLUX, STATUS = SCHEMAS


#: CDR's encapsulation header: plain little-endian CDR (XCDR1), no options.
CDR_LE = b"\x00\x01\x00\x00"
_STAMP = struct.Struct("<iI")  # builtin_interfaces/Time: int32 sec, uint32 nanosec
_WRENCH = struct.Struct("<6d")
_STATUS = struct.Struct("<QII")  # SampleStatus after its header: uint64 seq, uint32 flags, uint32 missed


class Stamped:
    """CDR (little-endian) of messages that start with a std_msgs/Header whose frame_id is
    ``frame_id`` and go on with an 8-byte member (a float64 or uint64: every message here):
    the header's bytes after the stamp are made once, padded so that member is 8-aligned
    (CDR aligns from after the 4-byte encapsulation), and a message is a concatenation."""

    def __init__(self, frame_id: str):
        text = frame_id.encode() + b"\0"
        string = struct.pack("<I", len(text)) + text
        self.tail = string + b"\0" * (-(_STAMP.size + len(string)) % 8)

    def message(self, t_wall: float, body: bytes) -> bytes:
        """The message stamped ``t_wall`` (UNIX s) whose members after the header are ``body``."""
        return CDR_LE + _STAMP.pack(*stamp(t_wall)) + self.tail + body


def stamp(t_wall: float) -> tuple[int, int]:
    """(sec, nanosec) of a UNIX time in seconds, as builtin_interfaces/Time."""
    return divmod(round(t_wall * 1e9), 1_000_000_000)


def encode_wrench(t_wall: float, frame_id: str, values: object) -> bytes:
    return Stamped(frame_id).message(t_wall, _WRENCH.pack(*(float(v) for v in values)))  # type: ignore[attr-defined]


def encode_field(t_wall: float, frame_id: str, b: object) -> bytes:
    values = [float(v) for v in b] + [0.0] * 9  # type: ignore[attr-defined]  # the field, then its covariance
    return Stamped(frame_id).message(t_wall, struct.pack("<12d", *values))


def missed_since(last: int | None, seq: int) -> int:
    """Sequence numbers skipped between a stream's previous sample ``last`` (None: none yet)
    and this one, ``seq``; 0 when it went back (a restarted daemon: nothing known skipped)."""
    return seq - last - 1 if last is not None and seq > last + 1 else 0


def status_body(seq: int, flags: int, missed: int) -> bytes:
    """A SampleStatus's members after its header (``missed`` held to its uint32)."""
    return _STATUS.pack(seq, flags, min(missed, 2**32 - 1))


def encode_status(t_wall: float, frame_id: str, seq: int, flags: int, missed: int) -> bytes:
    return Stamped(frame_id).message(t_wall, status_body(seq, flags, missed))


#: The sigma of a wrench whose companion did not come: unknown (as the wire's NaN).
_NO_SIGMA = (float("nan"),) * 6


def ros2_messages(sample: wire.Sample, frame: str, last_seq: int | None) -> list[tuple[str, str, str, bytes]]:
    """One sample as ROS 2 messages, ``(topic, schema, frame_id, CDR)``: a wrench's
    ``WrenchStamped`` and its sigma's on ``<topic>/sigma`` (or a ``MagneticField`` per chip
    of a flux stream) in ``frame``, then its ``SampleStatus`` (missed: sequence numbers
    after ``last_seq``, the stream's previous)."""
    topic, t = "/" + sample.topic, sample.t_wall
    out = []
    if sample.kind == wire.KIND_WRENCH:
        out.append((topic, WRENCH, frame, encode_wrench(t, frame, sample.values)))
        sigma = _NO_SIGMA if sample.sigma is None else sample.sigma
        out.append((f"{topic}/sigma", WRENCH, frame, encode_wrench(t, frame, sigma)))
    elif sample.kind == wire.KIND_SIGMA:  # a companion recorded as a stream of its own
        out.append((topic, WRENCH, frame, encode_wrench(t, frame, sample.values)))
    else:
        sensor = sample.topic.split("/", 1)[-1]
        for i in range(len(sample.values) // 3):
            chip_frame = f"{sensor}/chip{i}"
            out.append(
                (
                    f"{topic}/chip{i}",
                    FLUX,
                    chip_frame,
                    encode_field(t, chip_frame, sample.values[3 * i : 3 * i + 3]),
                )
            )
    missed = missed_since(last_seq, sample.seq)
    out.append((f"{topic}/status", STATUS, frame, encode_status(t, frame, sample.seq, sample.flags, missed)))
    return out


class McapWriter:
    """Samples of any streams into one MCAP file; the recorder's `flush` closes a chunk."""

    def __init__(self, path: str | Path, frames: dict[str, str]):
        try:
            from mcap.writer import CompressionType, Writer
        except ImportError as exc:
            raise ConfigError(
                "recording MCAP needs the mcap package: pip install 'ftsensord[record]'"
            ) from exc
        self.path, self.frames = Path(path), frames
        self.file = open(self.path, "wb")
        # zstd per chunk; a chunk is cut by time (flush), so its size bound rarely acts.
        self.writer = Writer(self.file, compression=CompressionType.ZSTD)
        self.writer.start(profile="ros2", library=f"ftsensord {__version__}")
        self.schemas = {
            name: self.writer.register_schema(name, "ros2msg", text.encode())
            for name, text in SCHEMAS.items()
        }
        self.channels: dict[str, int] = {}
        self.last_seq: dict[str, int] = {}

    def _channel(self, topic: str, schema: str, frame: str) -> int:
        if topic not in self.channels:
            self.channels[topic] = self.writer.register_channel(
                topic, "cdr", self.schemas[schema], {"frame_id": frame}
            )
        return self.channels[topic]

    def _add(self, topic: str, schema: str, frame: str, t_ns: int, seq: int, data: bytes) -> None:
        # MCAP's sequence field is u32: the low bits; the status message has all 64.
        self.writer.add_message(self._channel(topic, schema, frame), t_ns, data, t_ns, seq & 0xFFFFFFFF)

    def write(self, sample: wire.Sample) -> None:
        last = self.last_seq.get(sample.topic)
        self.last_seq[sample.topic] = sample.seq
        t_ns = round(sample.t_wall * 1e9)
        for topic, schema, frame, data in ros2_messages(
            sample, self.frames.get(sample.topic, sample.topic), last
        ):
            self._add(topic, schema, frame, t_ns, sample.seq, data)

    def flush(self) -> None:
        self.writer.flush()  # closes the chunk, writes it and its index, flushes the file

    def close(self, tallies: Mapping[str, Any]) -> None:
        """Write the summary (with each stream's samples, missed and frame as metadata)."""
        self.writer.add_metadata(
            "ftsensord",
            {
                "version": __version__,
                **{f"{s}.samples": str(t.samples) for s, t in tallies.items()},
                **{f"{s}.missed": str(t.gaps) for s, t in tallies.items()},
                **{f"{s}.frame": self.frames.get(s, s) for s in tallies},
            },
        )
        self.writer.finish()
        self.file.close()


def frames_from_status(status: dict, streams: list[str]) -> dict[str, str]:
    """Each stream's frame as the daemon's status names it; the stream's own name
    where it names none (a wrench's numbers are in *some* frame: better a name
    that says whose than an invented one)."""
    named: dict = status["frames"] if isinstance(status.get("frames"), dict) else {}
    sensors: dict = status["sensors"] if isinstance(status.get("sensors"), dict) else {}
    frames = {}
    for stream in streams:
        kind, _, name = stream.partition("/")
        frame = named.get(stream) or (sensors.get(name, {}).get("frame") if kind == "wrench" else None)
        frames[stream] = str(frame) if frame else stream
    return frames


def read_mcap(path: str | Path, decode: bool = True) -> Iterator[tuple[str, Any, int]]:
    """``(topic, message, log_time_ns)`` of every message of an MCAP file, in file
    order, ROS 2 messages decoded (``decode=False``: raw bytes). A file cut short
    (a killed recorder) yields every message of its complete chunks and stops at
    the tear; a complete file reads wholly."""
    from mcap.exceptions import McapError
    from mcap.reader import NonSeekingReader

    factories = []
    if decode:
        from mcap_ros2.decoder import DecoderFactory

        factories = [DecoderFactory()]
    with open(path, "rb") as f:
        reader = NonSeekingReader(f, decoder_factories=factories)
        messages = (
            reader.iter_decoded_messages(log_time_order=False)
            if decode
            else ((s, c, m, m.data) for s, c, m in reader.iter_messages(log_time_order=False))
        )
        try:
            for _schema, channel, message, decoded in messages:
                yield channel.topic, decoded, message.log_time
        except (McapError, struct.error, EOFError, ValueError):
            return  # the tear: a record cut by the kill


def recover_mcap(src: str | Path, dst: str | Path) -> int:
    """Rewrite an MCAP cut short (no summary, torn end) as a complete, indexed
    file; return the messages kept. (The mcap CLI's ``mcap recover`` does the same.)"""
    from mcap.exceptions import McapError
    from mcap.records import Channel, Message, Schema
    from mcap.stream_reader import StreamReader
    from mcap.writer import Writer

    kept = 0
    with open(src, "rb") as f, open(dst, "wb") as out:
        writer = Writer(out)
        writer.start(profile="ros2", library=f"ftsensord {__version__} (recovered)")
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        try:
            for r in StreamReader(f, skip_magic=False, emit_chunks=False).records:
                if isinstance(r, Schema):
                    schemas.setdefault(r.id, writer.register_schema(r.name, r.encoding, r.data))
                elif isinstance(r, Channel) and r.id not in channels:
                    channels[r.id] = writer.register_channel(
                        r.topic, r.message_encoding, schemas.get(r.schema_id, 0), r.metadata
                    )
                elif isinstance(r, Message) and r.channel_id in channels:
                    writer.add_message(channels[r.channel_id], r.log_time, r.data, r.publish_time, r.sequence)
                    kept += 1
        except (McapError, struct.error, EOFError, ValueError):
            pass  # the tear
        writer.finish()
    return kept
