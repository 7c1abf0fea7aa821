"""``[ros2] output = "in-loop"``: the daemon's loop thread writes the samples to DDS itself.

After each cycle's ZeroMQ sends (`daemon.daemon.Daemon.cycle`'s ``outputs``), one
``ddspy_write`` a stream whose topic some reader reads: the WrenchStamped's CDR bytes are
made once a stream, and each cycle's stamp and six float64 are patched into them; its
SampleStatus likewise. No thread, no process, no ZeroMQ subscriber between the loop and
DDS. In the same place, outside every sample's path: which topics have readers (five
times a second), ``/diagnostics`` from the part of the daemon's status it shows (once a
second, over a few cycles: `daemon.status.health_reply` and the statuses in one, the message's
bytes, `diagnostics.Encoder`, a few statuses a cycle in the next, the write with the last),
and the inputs, taken without waiting (a waitset asked with a zero timeout): an orientation
goes to the daemon's orientation receiver as a message on its socket would, a tare to its
control socket from a thread of its own (it takes the tare's samples to answer).

DDS's own threads (receive, timed events, delivery, garbage) are made with the participant,
by a thread at the normal policy: under ``run --realtime`` they never run real-time, as in
the bridge process; only the writes run in the loop thread, at its priority.
"""

from __future__ import annotations

import logging
import os
import struct
import threading
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from ftsensord.daemon.status import health_reply, stream_frames
from ftsensord.errors import ConfigError
from ftsensord.protocol import orientation as wire_orientation
from ftsensord.recording.ros2mcap import missed_since, stamp, status_body
from ftsensord.ros2 import diagnostics
from ftsensord.ros2.bridge import DIAGNOSTICS_S, READERS_S, WRENCH_BYTES, tare

if TYPE_CHECKING:
    from ftsensord.config.ros2conf import Ros2Config
    from ftsensord.daemon.daemon import Daemon
    from ftsensord.processing.gravity import Compensated
    from ftsensord.processing.pipeline import SensorSample
    from ftsensord.ros2.node import Ros2Node

log = logging.getLogger("ftsensord.ros2")

_TIME = struct.Struct("<iI")  # builtin_interfaces/Time
STAMP_AT = 4  # header.stamp: right after CDR's 4-byte encapsulation
_STATUS_BODY = len(status_body(0, 0, 0))
#: /diagnostics' statuses encoded a cycle: 7 of the packaged configuration's 19 (the daemon,
#: 2 sensors, 16 chips) are about 0.6M instructions, less than the cycle that makes the
#: statuses (0.94M; benchmarks/performance/ros2_instructions.py), where all 19 at once were 2.2M.
DIAGNOSTICS_A_CYCLE = 7


def at_normal_policy(make: Any) -> Any:
    """``make()`` called in a thread of its own at SCHED_OTHER (the threads it starts inherit
    that policy, not the real-time loop's); its result, or its exception raised here."""
    out: dict[str, Any] = {}

    def body() -> None:
        try:
            if os.sched_getscheduler(0) != os.SCHED_OTHER:  # 0: this thread (Linux)
                os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
            out["made"] = make()
        except BaseException as exc:  # noqa: BLE001 (handed to the caller)
            out["error"] = exc

    thread = threading.Thread(target=body, name="ros2-setup")
    thread.start()
    thread.join()
    if "error" in out:
        raise out["error"]
    return out["made"]


class Stream:
    """One stream's writers and its two messages' bytes, patched in place each cycle."""

    def __init__(self, node: Ros2Node, topic: str):
        self.topic = topic  # the daemon's (``wrench/<name>``)
        wrench_writer, status_writer, cdr = node._writers(topic)  # noqa: SLF001 (the node's own table)
        self.wrench_writer, self.status_writer = wrench_writer, status_writer
        self.wrench_ref, self.status_ref = wrench_writer._ref, status_writer._ref  # noqa: SLF001 (for ddspy_write)
        self.sigma_writer = node.sigma_writers.get(topic)  # None: a stream without a sigma (`wire.has_sigma`)
        self.sigma_ref = None if self.sigma_writer is None else self.sigma_writer._ref  # noqa: SLF001
        self.wrench = bytearray(cdr.message(0.0, bytes(WRENCH_BYTES)))
        self.sigma = bytearray(self.wrench)  # the same layout: a WrenchStamped, its stamp and frame
        self.status = bytearray(cdr.message(0.0, status_body(0, 0, 0)))
        self.values_at, self.body_at = len(self.wrench) - WRENCH_BYTES, len(self.status) - _STATUS_BODY
        self.last_seq: int | None = None


class InLoop:
    """The daemon's streams on DDS domain ``ros2.domain_id``, written by its loop thread."""

    def __init__(self, daemon: Daemon, ros2: Ros2Config):
        from cyclonedds._clayer import ddspy_write  # the C call DataWriter.write ends in (node.py)
        from cyclonedds.core import DDSException

        from ftsensord.ros2.node import Ros2Node

        self.daemon, self.namespace, self.domain_id = daemon, ros2.namespace, ros2.domain_id
        frames = {s: f for s, f in stream_frames(daemon).items() if s.startswith("wrench/")}
        oriented = sorted(daemon.orientations.frames) if daemon.config.orientation_endpoint else []
        try:
            self.node = at_normal_policy(lambda: Ros2Node(ros2.namespace, ros2.domain_id, frames, oriented))
        except DDSException as exc:  # a bad CYCLONEDDS_URI, no usable interface: said, not a traceback
            raise ConfigError(
                f"ros2: no DDS participant on domain {ros2.domain_id} "
                f"(CYCLONEDDS_URI={os.environ.get('CYCLONEDDS_URI', '')!r}): {exc}"
            ) from exc
        self.streams = {topic: Stream(self.node, topic) for topic in frames}
        self.read: tuple[Stream, ...] = ()  # streams whose wrench or status some reader reads
        self.flags: dict[str, int] = {}  # each sensor's (and the tip's) latest flags, for the diagnostics
        self.ask = self.due = time.monotonic()
        self.pending: diagnostics.Encoder | None = None  # the /diagnostics being encoded
        self.write_errors = self.failures = 0
        self.ddspy_write = ddspy_write

    def after_sends(
        self,
        seq: int,
        t_wall: float,
        samples: dict[str, SensorSample],
        tip: tuple[np.ndarray, int] | None,
        compensated: list[Compensated],
    ) -> None:
        """A cycle's wrenches (N, Nm, each in its stream's frame), stamped ``t_wall`` (UNIX s), to
        the DDS readers; then, when due, readers, diagnostics and inputs. What fails in DDS is
        counted (the first logged), never raised into the loop: the ZeroMQ streams go on, as
        they do when the bridge process dies."""
        try:
            self._after_sends(seq, t_wall, samples, tip, compensated)
        except Exception as exc:  # noqa: BLE001 (any of DDS's or the binding's: the loop must not stop)
            self.failures += 1
            if self.failures == 1:
                log.error("the ROS 2 output failed (and any more failures, counted): %r", exc)

    def _after_sends(
        self,
        seq: int,
        t_wall: float,
        samples: dict[str, SensorSample],
        tip: tuple[np.ndarray, int] | None,
        compensated: list[Compensated],
    ) -> None:
        time_bytes = _TIME.pack(*stamp(t_wall))
        for name, s in samples.items():
            self.flags[name] = s.flags
        if tip is not None:
            self.flags["tip"] = tip[1]
        # Each wrench with its sigma (the daemon's, as on its companion stream; None: it has none)
        wrenches: list[tuple[str, int, np.ndarray, np.ndarray | None]] = [
            (f"wrench/{n}", s.flags, s.wrench, s.sigma.sigma) for n, s in samples.items()
        ]
        wrenches += [("wrench/tip", tip[1], tip[0], self.daemon.tip_sigma)] if tip is not None else []
        wrenches += compensated
        for topic, flags, values, sigma in wrenches:
            stream = self.streams.get(topic)
            if stream is None:
                continue  # a stream the configuration did not have at start (a reload): not on DDS
            last, stream.last_seq = stream.last_seq, seq
            if stream in self.read:
                self.write(stream, seq, last, time_bytes, flags, values, sigma)
        now = time.monotonic()
        if now >= self.ask:
            self.ask = now + READERS_S
            self.find_readers()
        # The diagnostics over a few cycles, so no cycle carries more than about 0.25 ms of
        # them: the daemon's health and its statuses in one, their bytes in the next ones.
        if self.pending is not None:
            if self.pending.add(DIAGNOSTICS_A_CYCLE):
                self.node.write_diagnostics(self.pending.message(t_wall))
                self.pending = None
        elif now >= self.due:
            self.due = max(self.due + DIAGNOSTICS_S, now)
            self.pending = diagnostics.Encoder(
                diagnostics.statuses(health_reply(self.daemon), self.flags, self.namespace)
            )
        self.node.serve(0.0, self.on_orientation, self.on_tare)

    def write(
        self,
        stream: Stream,
        seq: int,
        last: int | None,
        time_bytes: bytes,
        flags: int,
        values: np.ndarray,
        sigma: np.ndarray | None = None,
    ) -> None:
        """One stream's WrenchStamped, SampleStatus (``last``: its previous seq) and sigma's
        WrenchStamped (``sigma``: N, Nm; NaN unknown) on the writers some reader reads."""
        ddspy_write = self.ddspy_write
        if stream.wrench_writer in self.node.read:
            buf = stream.wrench
            buf[STAMP_AT : STAMP_AT + 8] = time_bytes
            buf[stream.values_at :] = values.astype("<f8", copy=False).tobytes()
            if ddspy_write(stream.wrench_ref, buf) < 0:
                self.write_errors += 1  # counted: the next sample is the newer one anyway
        if stream.status_writer in self.node.read:
            buf = stream.status
            buf[STAMP_AT : STAMP_AT + 8] = time_bytes
            buf[stream.body_at :] = status_body(seq, flags, missed_since(last, seq))
            if ddspy_write(stream.status_ref, buf) < 0:
                self.write_errors += 1
        if sigma is not None and stream.sigma_writer in self.node.read:
            buf = stream.sigma
            buf[STAMP_AT : STAMP_AT + 8] = time_bytes
            buf[stream.values_at :] = sigma.astype("<f8", copy=False).tobytes()
            if ddspy_write(stream.sigma_ref, buf) < 0:
                self.write_errors += 1

    def status(self) -> dict[str, Any]:
        """The `status` reply's part (``outputs``): what an operator checks when ROS sees nothing."""
        return {
            "output": "in-loop",
            "namespace": self.namespace,
            "domain_id": self.domain_id,
            "streams_read": sorted(s.topic for s in self.read),
            "write_errors": self.write_errors,
            "failures": self.failures,
        }

    def find_readers(self) -> None:
        self.node.find_readers()
        self.read = tuple(
            s
            for s in self.streams.values()
            if s.wrench_writer in self.node.read
            or s.status_writer in self.node.read
            or s.sigma_writer in self.node.read
        )

    def on_orientation(self, frame: str, q_xyzw: list[float], t: float) -> None:
        """As the orientation socket's message: the receiver checks the frame and the rotation."""
        try:
            message = wire_orientation.encode(frame, np.array([q_xyzw[3], *q_xyzw[:3]]), t)
        except ValueError as exc:
            log.warning("orientation of %s from ROS refused: %s", frame, exc)
            return
        self.daemon.orientations.take([message], self.daemon.clock())

    def on_tare(self) -> tuple[bool, str]:
        """In the thread the node starts for a tare: lowered to the normal policy first (it
        was made by the loop's thread), then a control client of its own asks the daemon."""
        try:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        except OSError:
            pass  # left at the loop's policy: it waits on a socket almost all the time
        return tare(self.daemon.config.control)
