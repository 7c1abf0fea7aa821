"""Client library: subscribe to the daemon's streams, and control it.

    from ftsensord.client import Subscriber, ControlClient

    with Subscriber(streams=["wrench/sensor1"], latest=True) as sub:
        for sample in sub:              # the newest ftsensord.wire.Sample; N, Nm
            print(sample.seq, sample.values)

    ControlClient().tare(samples=100)

Endpoints default to the daemon's: the service's /run/ftsensord, else the
user's runtime folder (see `ftsensord.protocol.paths.runtime_dir`).
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import zmq

from ftsensord.docfile import parse_json
from ftsensord.errors import ConfigError, ControlError, DaemonNotAnswering, FtsensordError, WireError
from ftsensord.protocol import wire
from ftsensord.protocol.endpoints import needs_ipv6
from ftsensord.protocol.paths import check_private_dir, runtime_dir

#: Samples a recording subscriber may queue: 10 s of five streams at 100 Hz.
QUEUE_HWM = 5000
#: Where the systemd unit's RuntimeDirectory puts the sockets.
SERVICE_RUNTIME_DIR = Path("/run/ftsensord")


def default_endpoint(name: str) -> str:
    """``ipc://.../<name>`` of a running daemon: the service's if its socket
    exists, else this user's runtime folder. A folder someone else could have put
    sockets in (a symlink, another user's, writable by others) is refused with
    ConfigError: a client must never read a wrench from an impostor."""
    if os.path.lexists(SERVICE_RUNTIME_DIR / name):
        # Made by systemd for the service's user: any owner, but in root's /run.
        check_private_dir(SERVICE_RUNTIME_DIR, owner=-1)
        return f"ipc://{SERVICE_RUNTIME_DIR / name}"
    folder = runtime_dir()
    if os.path.lexists(folder):
        check_private_dir(folder)
    return f"ipc://{folder / name}"


def connect(sock: zmq.Socket, endpoint: str) -> None:
    """``sock.connect(endpoint)``; an endpoint ZeroMQ cannot parse is a ConfigError naming it
    (the socket closed), not a ZMQError traceback out of every command."""
    if needs_ipv6(endpoint):
        sock.setsockopt(zmq.IPV6, 1)
    try:
        sock.connect(endpoint)
    except zmq.ZMQError as exc:
        sock.close(linger=0)
        raise ConfigError(
            f"{endpoint}: ZeroMQ cannot connect to it ({exc.strerror}); "
            "expected ipc://PATH or tcp://HOST:PORT"
        ) from exc


class ControlClient:
    """JSON requests to the daemon's control endpoint (a fresh REQ socket each,
    so a timed-out request never wedges the next)."""

    def __init__(
        self,
        endpoint: str | None = None,
        timeout_s: float = 3.0,
        context: zmq.Context | None = None,
        curve: tuple[str, str] | None = None,
    ):
        """``curve``: (this client's certificate with its secret key, the server's
        public certificate), for a daemon whose control endpoint uses CURVE."""
        self.endpoint = endpoint or default_endpoint("control")
        self.timeout_s = timeout_s
        self.context = context or zmq.Context.instance()
        self.curve = curve

    def request(self, cmd: str, timeout_s: float | None = None, **args: Any) -> Any:
        """Send ``{"cmd": cmd, **args}``; return the reply's result.

        Raises `DaemonNotAnswering` after the timeout, `ControlError` when the
        daemon refuses.
        """
        socket = self.context.socket(zmq.REQ)
        socket.setsockopt(zmq.LINGER, 0)
        if self.curve is not None:
            from zmq.auth import load_certificate

            socket.curve_publickey, socket.curve_secretkey = load_certificate(self.curve[0])
            socket.curve_serverkey, _ = load_certificate(self.curve[1])
        try:
            connect(socket, self.endpoint)
            socket.send(json.dumps({"cmd": cmd, **args}).encode())
            wait = self.timeout_s if timeout_s is None else timeout_s
            if not socket.poll(int(wait * 1000)):
                raise DaemonNotAnswering(
                    f"no ftsensord answered on {self.endpoint} within {wait:g} s "
                    "(is it running? `systemctl status ftsensord`)"
                )
            raw = socket.recv()
        finally:
            socket.close()
        try:
            reply = parse_json(raw)
        except ConfigError as exc:
            reply = exc
        if not isinstance(reply, dict):  # not the daemon's (another program there), or corrupted
            raise ControlError(f"the reply on {self.endpoint} is not a JSON object: {str(reply)[:120]}")
        if not reply.get("ok"):
            raise ControlError(reply.get("error", "the daemon refused the request"))
        return reply.get("result")

    def status(self) -> dict[str, Any]:
        return self.request("status")

    def tare(self, samples: int = 100, sensor: str | None = None) -> dict[str, Any]:
        """Zero the output on the next ``samples`` cycles; waits for them."""
        args: dict[str, Any] = {"samples": samples}
        if sensor:
            args["sensor"] = sensor
        return self.request("tare", timeout_s=self.timeout_s + samples * 0.1, **args)

    def untare(self, sensor: str | None = None) -> dict[str, Any]:
        """Back to the calibration's own zero (every sensor, or ``sensor``); returns the
        wrench (N, Nm) each tare had removed, by sensor."""
        args: dict[str, Any] = {"sensor": sensor} if sensor else {}
        return self.request("untare", **args)

    def reload(self) -> dict[str, Any]:
        return self.request("reload")

    def set(self, **settings: Any) -> dict[str, Any]:
        return self.request("set", **settings)


def control_beside(endpoint: str | None, control: str | None = None) -> str | None:
    """The control endpoint of the daemon that publishes on ``endpoint``: ``control`` when
    given, the default one beside the default endpoint, the ``control`` socket in an ipc
    endpoint's folder (the daemon's sockets share it); None for another transport, whose
    daemon may be on another host."""
    if control is not None:
        return control
    if endpoint is None:
        return default_endpoint("control")
    if endpoint.startswith("ipc://"):
        return endpoint.rsplit("/", 1)[0] + "/control"
    return None


def check_streams(
    streams: Sequence[str], endpoint: str | None, control: str | None = None, timeout_s: float = 1.0
) -> dict[str, Any] | None:
    """Refuse (`ConfigError`) a stream the daemon does not publish, naming those it does
    (its status's ``streams``): a misspelt name is otherwise only a wait for nothing.
    Returns the status, or None when no daemon could be asked or none answered; then,
    and while a daemon just started has published nothing yet, nothing is refused."""
    where = control_beside(endpoint, control)
    if where is None:
        return None
    try:
        status = ControlClient(where, timeout_s=timeout_s).status()
    except FtsensordError:
        return None
    refuse_unpublished(streams, status, where)
    return status


def refuse_unpublished(streams: Sequence[str], status: dict[str, Any], control: str) -> None:
    """`ConfigError` for the streams that the daemon whose ``status`` this is (asked on
    ``control``) does not publish, naming those it does; nothing when its status names
    none (a daemon before its first cycle)."""
    published = status.get("streams")
    if not isinstance(published, list) or not published:
        return
    unknown = [s for s in streams if s and s not in published]
    if unknown:
        raise ConfigError(
            f"{', '.join(unknown)}: not a stream the daemon on {control} publishes; "
            f"it publishes: {', '.join(map(str, published))}"
        )


class Subscriber:
    """Decoded samples of some streams (``None``: all), with gap counting.

    Two modes. ``latest=True`` (a haptic loop): one conflating socket per
    stream, so `receive` always gives the newest sample and never a backlog;
    the sequence numbers count what was skipped. ``latest=False`` (recording):
    one socket with a deep queue, so a reader that keeps up gets every sample.
    ZeroMQ drops the *newest* messages when a queue is full, which is why the
    haptic mode conflates rather than keeping a short queue.

    A wrench's sigma (its companion stream ``sigma/<stream>``, sent just before it) is
    received beside it and given as ``sample.sigma`` (6 values, N and Nm; NaN: unknown), or
    None when it did not come (a daemon that does not send it, or, in latest mode, when it
    has not yet arrived). The companions are not returned as samples of their own unless
    asked for by name.
    """

    def __init__(
        self,
        endpoint: str | None = None,
        streams: Sequence[str] | None = None,
        *,
        latest: bool = False,
        context: zmq.Context | None = None,
    ):
        self.endpoint = endpoint or default_endpoint("wrench")
        self.context = context or zmq.Context.instance()
        if latest and not streams:
            raise ValueError("latest=True needs the streams named (one conflating socket each)")
        groups = [[stream] for stream in streams or []] if latest else [list(streams or [""])]
        named = set(streams or [])
        #: The companions received for their wrench, not returned (by their topic).
        self._companions = {
            wire.SIGMA_PREFIX + s
            for s in (streams or [])
            if s.startswith("wrench/") and wire.SIGMA_PREFIX + s not in named
        }
        if streams is None:
            self._companions_all = True
        else:
            self._companions_all = False
            if not latest:
                groups[0] += sorted(self._companions)
        self.sockets = []
        self._sigma_sockets: dict[str, zmq.Socket] = {}
        for group in groups:
            sock = self.context.socket(zmq.SUB)
            sock.setsockopt(zmq.LINGER, 0)
            if latest:
                sock.setsockopt(zmq.CONFLATE, 1)
            else:
                sock.setsockopt(zmq.RCVHWM, QUEUE_HWM)
            for stream in group:
                # The NUL after the topic makes "wrench/sensor1" not match "wrench/sensor10".
                sock.setsockopt(zmq.SUBSCRIBE, stream.encode() + b"\0" if stream else b"")
            try:
                connect(sock, self.endpoint)
            except ConfigError:
                self.close()  # the ones opened before it
                raise
            self.sockets.append(sock)
        if latest:  # a conflating socket of each companion, read when its wrench comes
            for topic in sorted(self._companions):
                sock = self.context.socket(zmq.SUB)
                sock.setsockopt(zmq.LINGER, 0)
                sock.setsockopt(zmq.CONFLATE, 1)
                sock.setsockopt(zmq.SUBSCRIBE, topic.encode() + b"\0")
                try:
                    connect(sock, self.endpoint)
                except ConfigError:
                    self.close()
                    raise
                self._sigma_sockets[topic] = sock
        self._sigmas: dict[str, tuple[int, np.ndarray]] = {}  # the last companion of each wrench
        self.poller = zmq.Poller()
        for sock in self.sockets:
            self.poller.register(sock, zmq.POLLIN)
        self.last_seq: dict[str, int] = {}
        self.gaps: dict[str, int] = {}
        self.received = 0

    def receive(self, timeout_s: float | None = None) -> wire.Sample | None:
        """The next sample (in latest mode: the newest of a stream that has one),
        or None after ``timeout_s`` (None: wait forever)."""
        while True:
            ready = dict(self.poller.poll(None if timeout_s is None else int(timeout_s * 1000)))
            sock = next((s for s in self.sockets if s in ready), None)
            if sock is None:
                return None
            sample = wire.decode(sock.recv())
            if sample.kind != wire.KIND_SIGMA or not (
                sample.topic in self._companions or self._companions_all
            ):
                break
            # a companion: kept for its wrench (the next sample of that stream, same seq)
            self._sigmas[sample.topic] = (sample.seq, sample.values)
        if sample.kind == wire.KIND_WRENCH:
            sample = self._with_sigma(sample)
        last = self.last_seq.get(sample.topic)
        if last is not None and sample.seq > last + 1:
            self.gaps[sample.topic] = self.gaps.get(sample.topic, 0) + sample.seq - last - 1
        self.last_seq[sample.topic] = sample.seq
        self.received += 1
        return sample

    def _with_sigma(self, sample: wire.Sample) -> wire.Sample:
        """The wrench ``sample`` with its companion's sigma when one of its seq came."""
        topic = wire.SIGMA_PREFIX + sample.topic
        sock = self._sigma_sockets.get(topic)
        if sock is not None:  # latest mode: the newest companion, if any came since
            try:
                c = wire.decode(sock.recv(zmq.NOBLOCK))
                self._sigmas[topic] = (c.seq, c.values)
            except zmq.Again:
                pass
        found = self._sigmas.get(topic)
        if found is None or found[0] != sample.seq:
            return sample
        return dataclasses.replace(sample, sigma=found[1])

    def __iter__(self) -> Iterator[wire.Sample]:
        while True:
            sample = self.receive()
            if sample is not None:
                yield sample

    def close(self) -> None:
        for sock in [*self.sockets, *getattr(self, "_sigma_sockets", {}).values()]:
            sock.close()

    def __enter__(self) -> Subscriber:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class OrientationPublisher:
    """Tell the daemon how the tool is turned, for gravity compensation (docs/guide/clients.md).

        with OrientationPublisher() as pub:
            pub.send("sensor1", R_world_sensor)        # 3 x 3, or scipy's Rotation; or "tip"
            pub.send("sensor1", q_xyzw=rot.as_quat())  # a quaternion names its order: q_xyzw or q_wxyz

    A PUB socket connected to the daemon's orientation endpoint: a send never
    blocks (nothing is queued for a daemon not running), the daemon keeps the newest.
    """

    def __init__(self, endpoint: str | None = None, context: zmq.Context | None = None):
        from ftsensord.protocol import orientation

        self._encode = orientation.encode
        self.endpoint = endpoint or default_endpoint("orientation")
        self.socket = (context or zmq.Context.instance()).socket(zmq.PUB)
        self.socket.setsockopt(zmq.LINGER, 0)
        connect(self.socket, self.endpoint)

    def send(
        self,
        frame: str,
        rotation: Any = None,
        t_sender: float | None = None,
        *,
        q_wxyz: Any = None,
        q_xyzw: Any = None,
    ) -> None:
        """How ``frame`` is turned, R_world,frame (it takes the frame's vectors into the world),
        given as exactly one of: ``rotation``, a 3 x 3 matrix or an object with ``as_matrix()``
        (scipy's Rotation); ``q_wxyz``, a unit quaternion w first (Eigen's Quaterniond(w, x,
        y, z) constructor); ``q_xyzw``, w last (scipy's as_quat(), Eigen's coeffs(), ROS's
        geometry_msgs/Quaternion). A bare 4-vector as ``rotation`` is refused: sent in the
        wrong order it is a valid rotation, wrong by up to 180 deg, and right at the identity
        (so a check at rest passes). ``t_sender`` (s) defaults to this host's CLOCK_MONOTONIC."""
        import time

        given = [x is not None for x in (rotation, q_wxyz, q_xyzw)]
        if sum(given) != 1:
            raise WireError("orientation: give exactly one of rotation (3 x 3), q_wxyz or q_xyzw")
        if q_xyzw is not None:
            value = np.roll(
                np.asarray(q_xyzw, dtype=float).ravel(), 1
            )  # w last to w first; its size checked below
        elif q_wxyz is not None:
            value = np.asarray(q_wxyz, dtype=float).ravel()
        else:
            value = np.asarray(
                rotation.as_matrix() if hasattr(rotation, "as_matrix") else rotation, dtype=float
            )
            if value.size == 4:
                raise WireError(
                    "orientation: a quaternion's order is ambiguous: pass q_xyzw= (scipy's "
                    "as_quat(), Eigen's coeffs(), ROS's geometry_msgs/Quaternion) or q_wxyz= (w first)"
                )
        if value.size != (4 if rotation is None else 9):
            raise WireError(
                f"orientation: expected {'4 quaternion' if rotation is None else '3 x 3 matrix'} "
                f"values, got {value.size}"
            )
        t = time.monotonic() if t_sender is None else t_sender
        try:
            self.socket.send(self._encode(frame, value, t), zmq.NOBLOCK)
        except zmq.Again:
            pass  # the queue is full: latest value wins, the next send replaces it

    def close(self) -> None:
        self.socket.close(linger=0)

    def __enter__(self) -> OrientationPublisher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
