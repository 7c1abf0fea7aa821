"""The wire format of published samples (docs/reference/protocol.md has it byte by byte).

One ZeroMQ frame per sample: the topic (ASCII, e.g. ``wrench/sensor1``), one
NUL byte, then a 40-byte little-endian header and ``count`` float64 values.
A single frame lets a subscriber keep only the newest sample (ZMQ_CONFLATE),
and a C client decodes it with one memcpy per field.
"""

from __future__ import annotations

import functools
import struct
from dataclasses import dataclass

import numpy as np

from ftsensord.errors import WireError

MAGIC = 0x5446  # b"FT" read as a little-endian u16
VERSION = 1
KIND_WRENCH = 1
KIND_FLUX = 2
#: A wrench's 1-sigma per axis (N, Nm; NaN unknown), on the topic `SIGMA_PREFIX` + the
#: wrench's, with its seq and flags, sent just before the wrench (docs/reference/protocol.md).
KIND_SIGMA = 3
SIGMA_PREFIX = "sigma/"


def has_sigma(stream: str) -> bool:
    """Whether the daemon sends a sigma companion (`SIGMA_PREFIX` + ``stream``) with each
    sample of ``stream``: a sensor's wrench or the tip's (``wrench/<name>``) and their
    compensated ones (``wrench/<name>/compensated``), not flux."""
    kind, _, name = stream.partition("/")
    name = name.removesuffix("/compensated")
    return kind == "wrench" and bool(name) and "/" not in name


#: magic u16, version u8, kind u8, flags u32, seq u64, t_mono f64, t_wall f64,
#: count u16, reserved u16, reserved u32: 40 bytes, so the values start 8-aligned.
HEADER = struct.Struct("<HBBIQddHHI")
assert HEADER.size == 40

# Status flags: each marks every sample a condition affects.
FLAG_CHIP_MISSING = 1 << 0  # a chip did not answer this cycle
FLAG_SATURATED = 1 << 1  # a chip's reading was at or past its range
FLAG_STALE = 1 << 2  # a chip had no new data: its previous reading was used
FLAG_OVERLOAD = 1 << 3  # the wrench is beyond the sensor's range
FLAG_DEGRADED = 1 << 4  # estimated from fewer chips than calibrated
FLAG_LATE = 1 << 5  # the cycle began after its deadline
FLAG_INVALID = 1 << 6  # no estimate possible: the values are NaN
FLAG_FALLBACK = 1 << 7  # the nonlinear estimator did not converge: the linear estimate was used
FLAG_EXTRAPOLATED = 1 << 8  # a linear estimate beyond the loads the calibration was fitted on
FLAG_INCONSISTENT = (
    1 << 9
)  # the chips disagree beyond noise and model error (one stuck, drifted, or seeing a field alone)
FLAG_ORIENTATION_STALE = (
    1 << 10
)  # a compensated wrench: the orientation is older than stale_after_s, or unknown
FLAG_TEMPERATURE = 1 << 11  # a chip's temperature is beyond the span the temperature compensation covers

FLAG_NAMES = {
    FLAG_CHIP_MISSING: "chip_missing",
    FLAG_SATURATED: "saturated",
    FLAG_STALE: "stale",
    FLAG_OVERLOAD: "overload",
    FLAG_DEGRADED: "degraded",
    FLAG_LATE: "late",
    FLAG_INVALID: "invalid",
    FLAG_FALLBACK: "fallback",
    FLAG_EXTRAPOLATED: "extrapolated",
    FLAG_INCONSISTENT: "inconsistent",
    FLAG_ORIENTATION_STALE: "orientation_stale",
    FLAG_TEMPERATURE: "temperature",
}


def flag_names(flags: int) -> list[str]:
    return [name for bit, name in FLAG_NAMES.items() if flags & bit]


@dataclass(frozen=True)
class Sample:
    """One decoded sample. ``values``: a wrench [fx fy fz mx my mz] (N, Nm) in
    the stream's frame, or the raw flux of a sensor's chips (T, chip frames)."""

    topic: str
    kind: int
    seq: int
    t_mono: float
    t_wall: float
    flags: int
    values: np.ndarray
    #: A wrench's 1-sigma per axis (N, Nm; NaN: unknown), from its companion stream
    #: (`SIGMA_PREFIX`); None when the subscriber did not receive it (`client.Subscriber`).
    sigma: np.ndarray | None = None


_F8 = np.dtype("<f8")


def encode(
    topic: str, kind: int, seq: int, t_mono: float, t_wall: float, flags: int, values: np.ndarray
) -> bytes:
    # (tobytes is in C order whatever the layout; a daemon's own values are float64 already)
    if type(values) is not np.ndarray or values.dtype != _F8:
        values = np.asarray(values, dtype=_F8)
    return (
        _prefix(topic)
        + HEADER.pack(MAGIC, VERSION, kind, flags, seq, t_mono, t_wall, len(values), 0, 0)
        + values.tobytes()
    )


@functools.lru_cache(maxsize=256)
def _prefix(topic: str) -> bytes:
    """A topic's bytes and its NUL: the same few topics every cycle."""
    return topic.encode("ascii") + b"\0"


def unpack(frame: bytes) -> tuple[str, int, int, int, float, float, bytes]:
    """A frame's topic, kind, flags, seq, t_mono, t_wall (s) and its values as they are on the
    wire (``count`` little-endian float64), checked as `decode` checks them: for a forwarder
    that passes the values on as bytes (the ROS 2 bridge), without numpy's cost."""
    topic, sep, body = bytes(frame).partition(b"\0")
    if not sep or len(body) < HEADER.size:
        raise WireError("frame too short or without a topic")
    magic, version, kind, flags, seq, t_mono, t_wall, count, _, _ = HEADER.unpack_from(body)
    if magic != MAGIC or version != VERSION:
        raise WireError(f"not an ftsensord v{VERSION} sample (magic 0x{magic:04X}, version {version})")
    if len(body) != HEADER.size + 8 * count:
        raise WireError(f"{count} values announced, {(len(body) - HEADER.size) / 8:g} present")
    if (
        not topic.isascii()
    ):  # a stray publisher's frame: refused as any malformed one, not a UnicodeDecodeError
        raise WireError(f"the topic is not ASCII: {topic[:40]!r}")
    return topic.decode("ascii"), kind, flags, seq, t_mono, t_wall, body[HEADER.size :]


def decode(frame: bytes) -> Sample:
    topic, kind, flags, seq, t_mono, t_wall, values = unpack(frame)
    return Sample(topic, kind, seq, t_mono, t_wall, flags, np.frombuffer(values, dtype="<f8").copy())
