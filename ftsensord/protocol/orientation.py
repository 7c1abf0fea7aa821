"""The orientation stream: the haptic application tells the daemon how the tool is turned.

The application PUBlishes, the daemon SUBscribes on a socket it binds in its
runtime folder (``ipc://<runtime>/orientation``). PUB, not PUSH: a PUB send
never blocks a 1 kHz servo loop, whether the daemon runs, restarts or lags
(PUSH blocks, or fails, with no peer or a full queue), and a restarted daemon
is found again by ZeroMQ's reconnect. Latest value wins: each cycle the daemon
reads every queued message and keeps the newest per frame.

One frame per message, little-endian (docs/guide/clients.md has the byte table and a
test vector):

  offset  type      field
  0       char[4]   magic "FTOR"
  4       u8        version 1
  5       u8        representation: 1 quaternion [w x y z], 2 rotation matrix (row-major)
  6       u16       reserved, 0
  8       char[32]  frame: a sensor's name or "tip", ASCII, NUL-padded (31 characters at most)
  40      f64       t_sender: the sender's time (s, its own clock), reported in status
  48      f64[n]    n = 4 or 9: R_world,frame, which takes the frame's vectors into the world

A message that is not this exactly is dropped and counted by reason (`status`),
never raised out of the loop.
"""

from __future__ import annotations

import math
import struct
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import zmq

from ftsensord.errors import WireError

MAGIC = b"FTOR"
VERSION = 1
QUATERNION, MATRIX = 1, 2
HEADER = struct.Struct("<4sBBH32sd")
assert HEADER.size == 48
SIZES = {QUATERNION: HEADER.size + 4 * 8, MATRIX: HEADER.size + 9 * 8}
#: A quaternion whose norm is off 1 by more than this is refused, not normalised: float32
#: maths and an integrator renormalising now and then stay within 1e-5 of unit, while
#: a zero, uninitialised or mis-ordered buffer is far off. Within it, normalising leaves
#: the rotation as sent. A rotation matrix may differ from orthonormal (|R^T R - I|, largest
#: entry) by as much: its nearest rotation is then within 1e-3 rad of it, which moves a
#: 50 g tool's weight by 0.5 mN, a fiftieth of the wrench's noise.
UNIT_TOLERANCE = 1e-3
#: Messages read in one cycle at most (a flood is left to the socket's queue, which
#: drops what does not fit): 1000 is 10 cycles of a 1 kHz sender naming 100 frames.
MAX_PER_CYCLE = 1000
#: Largest message ZeroMQ accepts: a longer one disconnects its sender (before it takes memory).
#: The largest valid one (a matrix) is 48 + 72 bytes; with RCVHWM queued per connection and
#: 128 connections (`connections.MAX_CONNECTIONS`), a hostile sender pins at most 33 MB.
MAX_MESSAGE = 256
RCVHWM = 1000


def quaternion_matrix(q: np.ndarray) -> np.ndarray:
    """The rotation matrix of the unit quaternion ``q`` = [w x y z] (Hamilton)."""
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def encode(frame: str, R_or_q: np.ndarray, t_sender: float) -> bytes:
    """A message: ``R_or_q`` a quaternion [w x y z] (4) or a rotation matrix (3 x 3)."""
    values = np.asarray(R_or_q, dtype="<f8").ravel()
    rep = QUATERNION if values.size == 4 else MATRIX
    name = frame.encode("ascii")
    if len(name) > 31 or values.size not in (4, 9):
        raise ValueError("frame: 31 ASCII characters at most; a quaternion (4) or a 3 x 3 matrix")
    return HEADER.pack(MAGIC, VERSION, rep, 0, name, t_sender) + values.tobytes()


@dataclass(frozen=True)
class Orientation:
    frame: str
    R: np.ndarray  # R_world,frame
    t_sender: float


def decode(message: bytes) -> Orientation:
    """One message; WireError whose first word is the reason (counted in `status`)."""
    if len(message) < HEADER.size:
        raise WireError(f"size: {len(message)} bytes, shorter than the 48-byte header")
    magic, version, rep, _, name, t_sender = HEADER.unpack_from(message)
    if magic != MAGIC:
        raise WireError(f"magic: {magic!r}, not {MAGIC!r}")
    if version != VERSION:
        raise WireError(f"version: {version}, not {VERSION}")
    if rep not in SIZES:
        raise WireError(f"representation: {rep}, not 1 (quaternion) or 2 (matrix)")
    if len(message) != SIZES[rep]:
        raise WireError(f"size: {len(message)} bytes, not {SIZES[rep]}")
    frame = name.rstrip(b"\0")
    if not frame or b"\0" in frame or not frame.isascii():
        raise WireError("frame: not an ASCII name, NUL-padded")
    values = np.frombuffer(message, dtype="<f8", offset=HEADER.size)
    if not (np.all(np.isfinite(values)) and math.isfinite(t_sender)):
        raise WireError("not_finite: a NaN or infinite value")
    if rep == QUATERNION:
        norm = float(np.linalg.norm(values))
        if abs(norm - 1.0) > UNIT_TOLERANCE:
            raise WireError(f"not_unit: quaternion norm {norm:.6g}")
        R = quaternion_matrix(values / norm)
    else:
        M = values.reshape(3, 3)
        if np.max(np.abs(M.T @ M - np.eye(3))) > UNIT_TOLERANCE or np.linalg.det(M) <= 0:
            raise WireError("not_unit: not a rotation matrix (orthonormal, determinant +1)")
        u, _, vt = np.linalg.svd(M)
        R = u @ vt  # the nearest rotation
    return Orientation(frame.decode("ascii"), R, float(t_sender))


@dataclass(frozen=True)
class Received:
    R: np.ndarray  # R_world,frame
    t_arrival: float  # s, the daemon's clock
    t_sender: float


class OrientationReceiver:
    """The daemon's end: `drain` each cycle; `latest` by frame; `dropped` by reason."""

    def __init__(self, socket: zmq.Socket | None, frames: set[str]):
        self.socket = socket
        self.frames = frames
        self.latest: dict[str, Received] = {}
        self.received = 0
        self.dropped: Counter[str] = Counter()

    def drain(self, now: float) -> None:
        """Read what is queued (at most `MAX_PER_CYCLE`), keep the newest per frame."""
        if self.socket is None:
            return
        for _ in range(MAX_PER_CYCLE):
            try:
                parts = self.socket.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                return
            self.take(parts, now)

    def take(self, parts: list[bytes], now: float) -> None:
        try:
            if len(parts) != 1:
                raise WireError(f"parts: {len(parts)} frames, not 1")
            o = decode(parts[0])
            if o.frame not in self.frames:
                raise WireError(f"unknown_frame: {o.frame!r}")
        except WireError as exc:
            self.dropped[str(exc).split(":", 1)[0]] += 1
            return
        self.received += 1
        self.latest[o.frame] = Received(o.R, now, o.t_sender)

    def status(self, now: float) -> dict[str, object]:
        return {
            "received": self.received,
            "dropped": dict(self.dropped),
            "frames": {
                f: {"age_s": round(now - r.t_arrival, 6), "t_sender": r.t_sender}
                for f, r in self.latest.items()
            },
        }


def open_receiver(context: zmq.Context, endpoint: str, bind: Callable[[zmq.Socket, str], None]) -> zmq.Socket:
    """The daemon's SUB socket, bound on ``endpoint`` with ``bind`` (`run.bind`: a checked folder)."""
    sock = context.socket(zmq.SUB)
    sock.setsockopt(zmq.SUBSCRIBE, b"")
    sock.setsockopt(zmq.RCVHWM, RCVHWM)
    sock.setsockopt(zmq.MAXMSGSIZE, MAX_MESSAGE)
    sock.setsockopt(zmq.LINGER, 0)
    bind(sock, endpoint)
    return sock
