"""Client library: subscribe to the daemon's streams, and control it.

    from ftsensord.client import Subscriber, ControlClient

    with Subscriber(streams=["wrench/sensor1"]) as sub:
        for sample in sub:              # ftsensord.wire.Sample; values in N, Nm
            print(sample.seq, sample.values)

    ControlClient().tare(samples=100)

Endpoints default to the daemon's: the service's /run/ftsensord, else the
user's runtime folder (see `ftsensord.config.runtime_dir`).
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import zmq

from . import wire
from .config import runtime_dir
from .errors import ControlError, DaemonNotAnswering

#: Where the systemd unit's RuntimeDirectory puts the sockets.
SERVICE_RUNTIME_DIR = Path("/run/ftsensord")


def default_endpoint(name: str) -> str:
    """``ipc://.../<name>`` of a running daemon: the service's if its socket
    exists, else this user's runtime folder."""
    for folder in (SERVICE_RUNTIME_DIR, runtime_dir()):
        if (folder / name).exists():
            return f"ipc://{folder / name}"
    return f"ipc://{runtime_dir() / name}"


class ControlClient:
    """JSON requests to the daemon's control endpoint (a fresh REQ socket each,
    so a timed-out request never wedges the next)."""

    def __init__(self, endpoint: str | None = None, timeout_s: float = 3.0, context: zmq.Context | None = None):
        self.endpoint = endpoint or default_endpoint("control")
        self.timeout_s = timeout_s
        self.context = context or zmq.Context.instance()

    def request(self, cmd: str, timeout_s: float | None = None, **args: Any) -> Any:
        """Send ``{"cmd": cmd, **args}``; return the reply's result.

        Raises `DaemonNotAnswering` after the timeout, `ControlError` when the
        daemon refuses.
        """
        socket = self.context.socket(zmq.REQ)
        socket.setsockopt(zmq.LINGER, 0)
        try:
            socket.connect(self.endpoint)
            socket.send(json.dumps({"cmd": cmd, **args}).encode())
            wait = self.timeout_s if timeout_s is None else timeout_s
            if not socket.poll(int(wait * 1000)):
                raise DaemonNotAnswering(f"no ftsensord answered on {self.endpoint} within {wait:g} s "
                                         "(is it running? `systemctl status ftsensord`)")
            reply = json.loads(socket.recv())
        finally:
            socket.close()
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

    def reload(self) -> dict[str, Any]:
        return self.request("reload")

    def set(self, **settings: Any) -> dict[str, Any]:
        return self.request("set", **settings)


class Subscriber:
    """Decoded samples of some streams (``None``: all), with gap counting.

    ``conflate`` keeps only the newest sample (for one stream only: ZeroMQ
    conflates across everything the socket receives).
    """

    def __init__(self, endpoint: str | None = None, streams: Sequence[str] | None = None, *,
                 conflate: bool = False, context: zmq.Context | None = None):
        self.endpoint = endpoint or default_endpoint("wrench")
        self.context = context or zmq.Context.instance()
        self.socket = self.context.socket(zmq.SUB)
        self.socket.setsockopt(zmq.LINGER, 0)
        if conflate:
            self.socket.setsockopt(zmq.CONFLATE, 1)
        else:
            self.socket.setsockopt(zmq.RCVHWM, 64)
        for stream in streams or [""]:
            # The NUL after the topic makes "wrench/sensor1" not match "wrench/sensor10".
            self.socket.setsockopt(zmq.SUBSCRIBE, stream.encode() + b"\0" if stream else b"")
        self.socket.connect(self.endpoint)
        self.last_seq: dict[str, int] = {}
        self.gaps: dict[str, int] = {}
        self.received = 0

    def receive(self, timeout_s: float | None = None) -> wire.Sample | None:
        """The next sample, or None after ``timeout_s`` (None: wait forever)."""
        if timeout_s is not None and not self.socket.poll(int(timeout_s * 1000)):
            return None
        sample = wire.decode(self.socket.recv())
        last = self.last_seq.get(sample.topic)
        if last is not None and sample.seq > last + 1:
            self.gaps[sample.topic] = self.gaps.get(sample.topic, 0) + sample.seq - last - 1
        self.last_seq[sample.topic] = sample.seq
        self.received += 1
        return sample

    def __iter__(self) -> Iterator[wire.Sample]:
        while True:
            sample = self.receive()
            if sample is not None:
                yield sample

    def close(self) -> None:
        self.socket.close()

    def __enter__(self) -> Subscriber:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
