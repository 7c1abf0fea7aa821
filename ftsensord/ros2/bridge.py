"""`ftsensord ros2`: the daemon's wrench streams on the ROS 2 graph (`node`), fed by ZeroMQ.

The bridge asks the daemon's status for its wrench streams and their frames (waiting for a
daemon still starting), subscribes to them, and writes each sample to DDS as it arrives, on
the topics some reader reads: the main thread does nothing else but, between two cycles,
ask DDS which topics have readers and, once a second, turn the daemon's status into
``/diagnostics``. Under a real-time daemon `run` gives this thread alone (and its ZeroMQ
I/O thread) SCHED_FIFO 1 (``--realtime``): on a busy host a sample then waits for the loop,
never for other processes (docs/results/performance.md, "ROS 2"). A second thread waits
on DDS's inputs (orientations, tare requests). An orientation from ROS goes to the daemon's
orientation socket as any client's would (`client.OrientationPublisher`); a tare to its
control socket (`client.ControlClient`).
`ftsensord run` starts this process when the configuration's ``[ros2]`` table says ``output = "bridge"``
(its default, ``"in-loop"``, writes from the daemon's loop instead: `inloop`).
"""

from __future__ import annotations

import argparse
import logging
import sys
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from ftsensord.errors import ConfigError, FtsensordError, WireError
from ftsensord.protocol import wire

if TYPE_CHECKING:
    from ftsensord.client import ControlClient

log = logging.getLogger("ftsensord.ros2")

#: Diagnostics period (s): REP 107 and diagnostic_updater publish at about 1 Hz.
DIAGNOSTICS_S = 1.0
#: How often the bridge asks DDS which topics have readers (s): a new subscriber's first
#: sample comes at most this late after discovery matched it.
READERS_S = 0.2
#: How long the input thread waits in DDS before looking at `done` (s).
INPUT_WAIT_S = 0.2
#: How long the forwarding thread waits for a sample before looking at `stopped` (ms).
POLL_MS = 200
#: A wrench's values on the wire: six float64.
WRENCH_BYTES = 6 * 8
#: Samples a tare from ROS averages (the Trigger request carries none): 1 s at 100 Hz, as `ftsensord tare`.
TARE_SAMPLES = 100


def wait_for_status(control: Any, stopped: Callable[[], bool], timeout_s: float) -> dict[str, Any] | None:
    """The daemon's status, asked until it answers with streams (a daemon starting with us),
    ConfigError after ``timeout_s``; None when ``stopped()`` first (a signal)."""
    end = time.monotonic() + timeout_s
    while not stopped():
        try:
            status = control.status()
            if status.get("streams"):
                return status
        except FtsensordError as exc:
            if time.monotonic() > end:
                raise ConfigError(
                    f"no daemon answered on {control.endpoint} in {timeout_s:g} s (--timeout); "
                    f"the last request: {exc}"
                ) from exc
        if time.monotonic() > end:
            raise ConfigError(f"the daemon on {control.endpoint} publishes no stream yet")
        time.sleep(0.2)
    return None


def tare(control: str) -> tuple[bool, str]:
    """A tare from ROS: the daemon on ``control`` asked by a client of its own (this runs in a
    thread of its own); whether it tared, and the Trigger response's message."""
    from ftsensord.client import ControlClient

    try:
        result = ControlClient(control, timeout_s=3.0).tare(samples=TARE_SAMPLES)
    except FtsensordError as exc:
        return False, f"tare refused: {exc}"
    return True, "tared " + ", ".join(
        f"{n} on {result['samples']} samples (removed " + " ".join(f"{v:+.4g}" for v in w) + " N, Nm)"
        for n, w in result["tare_wrench"].items()
    )


class Bridge:
    """The streams of the daemon on ``endpoint`` (its ``status`` asked of ``control``) on DDS
    domain ``domain_id``, until ``stopped()``."""

    def __init__(
        self,
        namespace: str,
        domain_id: int,
        endpoint: str,
        control: ControlClient,
        status: dict[str, Any],
        orientation: str | None,
        stopped: Callable[[], bool],
        realtime: int = 0,
    ):
        from ftsensord.client import OrientationPublisher
        from ftsensord.recording.ros2mcap import frames_from_status
        from ftsensord.ros2.node import Ros2Node

        self.stopped, self.realtime = stopped, realtime
        self.done = threading.Event()  # `run` has ended: the input thread ends too
        self.control = control
        self.streams = [s for s in status["streams"] if s.startswith("wrench/")]
        frames = frames_from_status(status, self.streams)
        oriented = sorted({*status.get("sensors", {}), *(["tip"] if "wrench/tip" in self.streams else [])})
        self.orientation = OrientationPublisher(orientation) if orientation else None
        self.endpoint, self.namespace = endpoint, namespace
        self.node = Ros2Node(namespace, domain_id, frames, oriented if orientation else [])
        self.flags: dict[str, int] = {}  # each sensor's latest wrench's flags, for the diagnostics
        self.bad_frames = 0
        self.sigmas: list[tuple[str, float, bytes]] = []  # the cycle's sigmas: written after its wrenches

    def on_orientation(self, frame: str, q_xyzw: list[float], t: float) -> None:
        if self.orientation is not None:
            try:
                self.orientation.send(frame, q_xyzw=q_xyzw, t_sender=t)
            except FtsensordError as exc:
                log.warning("orientation of %s from ROS refused: %s", frame, exc)

    def on_tare(self) -> tuple[bool, str]:
        return tare(self.control.endpoint)

    def inputs(self) -> None:
        """The second thread: DDS inputs as they come (it waits in DDS, the GIL released)."""
        while not self.done.is_set():
            self.node.serve(INPUT_WAIT_S, self.on_orientation, self.on_tare)

    def diagnose(self) -> None:
        """The daemon's status as /diagnostics (about 1 ms of Python: run between cycles, in
        the forwarding thread, so no sample waits for the GIL behind it)."""
        from ftsensord.ros2 import diagnostics

        try:
            status, why = self.control.status(), ""
        except FtsensordError as exc:
            status, why = None, str(exc)
        self.node.publish_diagnostics(
            diagnostics.statuses(status, self.flags, self.namespace, why), time.time()
        )

    def run(self, seconds: float | None = None) -> int:
        """Forward samples until ``stopped()`` (or ``seconds``); the number forwarded."""
        thread = threading.Thread(target=self.inputs, daemon=True)
        thread.start()
        end = None if seconds is None else time.monotonic() + seconds
        forwarded, due, ask = 0, time.monotonic(), time.monotonic()
        if self.realtime:  # this thread only: DDS's threads (made with the node) stay at the normal policy
            from ftsensord.daemon.realtime import request_fifo

            refused = request_fifo(self.realtime).refused
            if refused:
                log.warning(
                    "SCHED_FIFO %d for the forwarding refused (it runs at the normal priority): %s",
                    self.realtime,
                    refused,
                )
        sock = self.subscribe()
        try:
            while not self.stopped() and (end is None or time.monotonic() < end):
                # A cycle's streams come together: their wrenches first, as each arrives, then
                # their statuses, so no wrench waits behind another stream's status.
                cycle: list[Any] = []
                while sock.poll(0 if cycle else POLL_MS):
                    sample = self.forward(sock.recv())
                    if sample is not None:
                        cycle.append(sample)
                for topic, t_wall, seq, flags in cycle:
                    self.node.publish_status(topic, t_wall, seq, flags)
                    name = topic.partition("/")[2]
                    if "/" not in name:  # a sensor's own stream (or the tip's), not a compensated one
                        self.flags[name] = flags
                for topic, t_wall, values in self.sigmas:  # each sent before its wrench, written after
                    self.node.publish_sigma(topic, t_wall, values)
                self.sigmas.clear()
                forwarded += len(cycle)
                if time.monotonic() >= ask:  # between cycles, as the diagnostics
                    ask = time.monotonic() + READERS_S
                    self.node.find_readers()
                if time.monotonic() >= due:  # right after a cycle's samples: the next is a period away
                    due = max(due + DIAGNOSTICS_S, time.monotonic())
                    self.diagnose()
        finally:
            sock.close(linger=0)
            sock.context.term()
        self.done.set()
        thread.join(timeout=5)
        return forwarded

    def subscribe(self) -> Any:
        """A SUB socket on the wrench streams; its own context, so ZeroMQ's I/O thread is made now,
        by the forwarding thread (at its scheduling policy), not by the control client's."""
        import zmq

        from ftsensord.client import QUEUE_HWM

        sock = zmq.Context().socket(zmq.SUB)
        sock.setsockopt(zmq.RCVHWM, QUEUE_HWM)
        for stream in self.streams:
            sock.setsockopt(zmq.SUBSCRIBE, stream.encode() + b"\0")  # the NUL: not its longer namesakes
            if wire.has_sigma(stream):  # its sigma's companion, on the same socket: it comes first
                sock.setsockopt(zmq.SUBSCRIBE, (wire.SIGMA_PREFIX + stream).encode() + b"\0")
        sock.connect(self.endpoint)
        return sock

    def forward(self, frame: bytes) -> tuple[str, float, int, int] | None:
        """A frame's wrench written to DDS at once; its (topic, t_wall, seq, flags) for the status.
        A sigma is kept in `sigmas`, for after the cycle's wrenches (None returned)."""
        try:
            topic, kind, flags, seq, _, t_wall, values = wire.unpack(frame)
            if (
                kind == wire.KIND_SIGMA
                and topic.startswith(wire.SIGMA_PREFIX)
                and len(values) == WRENCH_BYTES
            ):
                self.sigmas.append((topic.removeprefix(wire.SIGMA_PREFIX), t_wall, values))
                return None
            if kind != wire.KIND_WRENCH or len(values) != WRENCH_BYTES:
                raise WireError(
                    f"kind {kind} with {len(values)} bytes of values, not a wrench's {WRENCH_BYTES}"
                )
        except WireError as exc:
            self.bad_frames += 1
            if self.bad_frames == 1:
                log.warning(
                    "a frame from %s is not a wrench sample, dropped (and any more, counted): %s",
                    self.endpoint,
                    exc,
                )
            return None
        self.node.publish_wrench(topic, t_wall, values)
        return topic, t_wall, seq, flags


def cmd_ros2(args: argparse.Namespace) -> int:
    from ftsensord.client import ControlClient, default_endpoint
    from ftsensord.config.file import load_config
    from ftsensord.config.ros2conf import (
        Ros2Config,
        check_domain_id,
        default_domain_id,
        is_ros_name,
        needs_cyclonedds,
    )
    from ftsensord.daemon.realtime import FIFO_PRIORITIES
    from ftsensord.recording import StopOnSignals

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    ros2, orientation = None, None
    endpoint, control = default_endpoint("wrench"), default_endpoint("control")
    if args.config:
        config = load_config(args.config)
        ros2 = config.ros2
        endpoint, control, orientation = config.publish[0], config.control, config.orientation_endpoint
    namespace = (args.namespace or (ros2 or Ros2Config()).namespace).strip("/")
    if not is_ros_name(namespace):
        raise ConfigError(f"--namespace: expected a ROS 2 name (letters, digits, _ and /), got {namespace!r}")
    domain_id = (
        check_domain_id("--domain-id", args.domain_id)
        if args.domain_id is not None
        else ros2.domain_id
        if ros2 is not None
        else default_domain_id()
    )
    if args.realtime and args.realtime not in FIFO_PRIORITIES:
        raise ConfigError(
            f"--realtime: expected a SCHED_FIFO priority from 1 to 99 (0: none), got {args.realtime}"
        )
    needs_cyclonedds("ftsensord ros2")
    with StopOnSignals() as stopped:  # from the start: a signal while it waits for the daemon stops it too
        client = ControlClient(
            args.control or control, timeout_s=min(3.0, args.timeout)
        )  # no request outlasts --timeout
        status = wait_for_status(client, stopped.is_set, args.timeout)
        if status is None:  # stopped before it was on the graph: nothing to undo
            return 130
        bridge = Bridge(
            namespace,
            domain_id,
            args.endpoint or endpoint,
            client,
            status,
            args.orientation or orientation,
            stopped.is_set,
            args.realtime,
        )
        print(
            f"ftsensord: ROS 2 bridge on DDS domain {domain_id}: "
            + ", ".join(f"/{namespace}/{s}" for s in bridge.streams)
            + f", /diagnostics, /{namespace}/tare",
            flush=True,
        )
        forwarded = bridge.run(args.seconds)
    print(
        f"ftsensord ros2: {forwarded} samples forwarded, {bridge.node.write_errors} writes failed, "
        f"{bridge.bad_frames} bad frames, "
        f"inputs {bridge.node.received}",
        file=sys.stderr,
    )
    return 0


def add_parser(sub: Any) -> None:
    """The ``ros2`` command (`cli.parser` calls this)."""
    p = sub.add_parser(
        "ros2",
        help="put the wrench streams on the ROS 2 graph (DDS, no ROS install needed)",
        description="The daemon's wrench streams as geometry_msgs/msg/WrenchStamped topics, "
        "/diagnostics, a tare service and orientation inputs, over Eclipse Cyclone "
        "DDS (the ros2 extra). docs/guide/ros2.md.",
    )
    p.add_argument("--config", help="the daemon's configuration: its endpoints and [ros2] table")
    p.add_argument("--namespace", help="topic namespace (default: [ros2] namespace, else ftsensord)")
    p.add_argument(
        "--domain-id", type=int, help="DDS domain (default: [ros2] domain_id, else $ROS_DOMAIN_ID, else 0)"
    )
    p.add_argument(
        "--endpoint", help="publish endpoint (default: the configuration's, else the running daemon's)"
    )
    p.add_argument(
        "--control", help="control endpoint (default: the configuration's, else the running daemon's)"
    )
    p.add_argument(
        "--orientation",
        help="the daemon's orientation endpoint (default: the configuration's; "
        "none: orientations from ROS are not read)",
    )
    p.add_argument("--seconds", type=float, help="stop after this long (default: until SIGTERM or Ctrl-C)")
    p.add_argument(
        "--realtime",
        type=int,
        default=0,
        metavar="PRIORITY",
        help="SCHED_FIFO priority of the forwarding thread (0: none; `run` gives 1 under a real-time "
        "daemon: below the loop, above normal processes)",
    )
    p.add_argument("--timeout", type=float, default=30.0, help="how long to wait for the daemon at start (s)")
    p.set_defaults(func=cmd_ros2)
