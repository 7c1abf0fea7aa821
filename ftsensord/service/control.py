"""The control endpoint: JSON requests in, JSON replies out, served between cycles.

`Control` parses a request, checks its arguments and hands it to the daemon's
matching method (the `Controlled` surface); whatever goes wrong becomes an
error reply, never an exception out of the loop. The socket is a ROUTER: a
request arrives as [identity, (empty), request], a reply goes back with the
same envelope.
"""

from __future__ import annotations

import json
import logging
from typing import Any, Protocol

import zmq

from ..errors import FtsensordError

log = logging.getLogger("ftsensord")

#: Largest control request accepted, bytes (ZMQ_MAXMSGSIZE drops larger ones).
MAX_REQUEST = 64 * 1024
COMMANDS = ("status", "tare", "reload", "set")


class Controlled(Protocol):
    """What the control requests act on (the daemon)."""

    sensor_names: list[str]

    def status(self) -> dict[str, Any]: ...

    def request_tare(self, envelope: list[bytes], sensors: list[str], samples: int) -> None: ...

    def reload(self) -> dict[str, Any]: ...

    def set_loop(self, rate_hz: float, averaging: int, lowpass_hz: float) -> dict[str, Any]: ...

    def loop_settings(self) -> tuple[float, int, float]: ...

    def set_estimator(self, estimator: str, sensor: str | None) -> dict[str, Any]: ...


class Control:
    """Answers control requests on ``socket`` (None: no endpoint) for ``target``."""

    def __init__(self, socket: zmq.Socket | None, target: Controlled):
        self.socket, self.target = socket, target

    def serve_waiting(self) -> None:
        """Answer every request waiting on the socket."""
        if self.socket is None:
            return
        while True:
            try:
                frames = self.socket.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                return
            if len(frames) < 2:
                continue  # not from a REQ or DEALER peer: nothing to answer to
            reply = self.handle(frames[-1], frames[:-1])
            if reply is not None:
                self.reply(frames[:-1], reply)

    def reply(self, envelope: list[bytes], reply: dict[str, Any]) -> None:
        if self.socket is None:
            return
        try:
            self.socket.send_multipart([*envelope, json.dumps(reply, default=float).encode()], zmq.NOBLOCK)
        except zmq.ZMQError:
            pass  # the peer left: nobody to tell

    def handle(self, raw: bytes, envelope: list[bytes]) -> dict[str, Any] | None:
        """One JSON request; returns the reply, or None when it comes later (tare)."""
        try:
            request = json.loads(raw)
        except (UnicodeDecodeError, json.JSONDecodeError, RecursionError):
            return {"ok": False, "error": "the request is not JSON"}
        if not isinstance(request, dict) or not isinstance(request.get("cmd"), str):
            return {"ok": False, "error": 'expected a JSON object with a string "cmd"'}
        handler = {"status": self._status, "tare": self._tare, "reload": self._reload,
                   "set": self._set}.get(request["cmd"])
        if handler is None:
            return {"ok": False, "error": f"unknown command {request['cmd'][:40]!r}; "
                                          f"commands: {', '.join(COMMANDS)}"}
        args = {k: v for k, v in request.items() if k != "cmd"}
        try:
            result = handler(args, envelope)
        except (FtsensordError, ValueError, TypeError) as exc:
            return {"ok": False, "error": str(exc)}
        except Exception:  # a bug must not stop the loop: log it, answer, go on
            log.exception("control request %r failed", request.get("cmd"))
            return {"ok": False, "error": "internal error (logged by the daemon)"}
        return None if result is None else {"ok": True, "result": result}

    @staticmethod
    def _only(args: dict[str, Any], allowed: set[str]) -> None:
        unknown = sorted(set(args) - allowed)
        if unknown:
            raise ValueError(f"unknown argument(s) {unknown}; this command takes {sorted(allowed) or 'none'}")

    def _sensor(self, name: object) -> str:
        if name not in self.target.sensor_names:
            raise ValueError(f"sensor: expected one of {self.target.sensor_names}, got {str(name)[:40]!r}")
        return str(name)

    def _status(self, args: dict[str, Any], envelope: list[bytes]) -> dict[str, Any]:
        self._only(args, set())
        return self.target.status()

    def _tare(self, args: dict[str, Any], envelope: list[bytes]) -> None:
        self._only(args, {"samples", "sensor"})
        samples = args.get("samples", 100)
        if not isinstance(samples, int) or isinstance(samples, bool) or not 1 <= samples <= 10_000:
            raise ValueError("samples: expected an integer from 1 to 10000")
        sensors = [self._sensor(args["sensor"])] if args.get("sensor") is not None else self.target.sensor_names
        self.target.request_tare(envelope, sensors, samples)
        return None

    def _reload(self, args: dict[str, Any], envelope: list[bytes]) -> dict[str, Any]:
        self._only(args, set())
        return self.target.reload()

    def _set(self, args: dict[str, Any], envelope: list[bytes]) -> dict[str, Any]:
        self._only(args, {"rate_hz", "averaging", "lowpass_hz", "estimator", "sensor"})
        if "estimator" in args:
            if set(args) - {"estimator", "sensor"}:
                raise ValueError("estimator: set it in a request of its own (with sensor, if any)")
            estimator = args["estimator"]
            if estimator not in ("linear", "nonlinear"):
                raise ValueError(f'estimator: expected "linear" or "nonlinear", got {str(estimator)[:40]!r}')
            sensor = self._sensor(args["sensor"]) if "sensor" in args and args["sensor"] is not None else None
            return self.target.set_estimator(estimator, sensor)
        if "sensor" in args:
            raise ValueError("sensor: goes with estimator only (rate, averaging and low-pass are the loop's)")
        rate, averaging, lowpass = self.target.loop_settings()
        rate = args.get("rate_hz", rate)
        averaging = args.get("averaging", averaging)
        lowpass = args.get("lowpass_hz", lowpass)
        if not isinstance(rate, (int, float)) or isinstance(rate, bool) or not 0.1 <= rate <= 10e3:
            raise ValueError("rate_hz: expected a number from 0.1 to 10000")
        if not isinstance(averaging, int) or isinstance(averaging, bool) or not 1 <= averaging <= 10_000:
            raise ValueError("averaging: expected an integer from 1 to 10000")
        if not isinstance(lowpass, (int, float)) or isinstance(lowpass, bool) or not 0 <= lowpass < rate / 2:
            raise ValueError(f"lowpass_hz: expected a number from 0 (off) to below half the rate ({rate / 2:g})")
        return self.target.set_loop(float(rate), averaging, float(lowpass))
