"""The control endpoint: JSON requests in, JSON replies out, served between cycles.

`Control` parses a request, checks its arguments and hands it to the daemon's
matching method (the `Controlled` surface); whatever goes wrong becomes an
error reply, never an exception out of the loop (the request is parsed within
limits: size, depth, integer length, `docfile.parse_json`). The socket is a
ROUTER: a request arrives as [identity, (empty), request], a reply goes back
with the same envelope. The loop comes first: each cycle answers what fits a
`Budget`, clients in turn, one request each per turn; a `status` is built once
per cycle.
"""

from __future__ import annotations

import json
import logging
import time
from collections import deque
from dataclasses import dataclass
from typing import Any, Protocol

import zmq

from ftsensord.docfile import parse_json
from ftsensord.errors import FtsensordError

log = logging.getLogger("ftsensord")

#: Largest control request accepted, bytes (ZMQ_MAXMSGSIZE drops larger ones).
MAX_REQUEST = 64 * 1024
COMMANDS = ("status", "tare", "untare", "reload", "set")
#: Deepest nesting in a request: the deepest valid request is a flat object (depth 1).
MAX_REQUEST_DEPTH = 8
#: Requests answered per cycle at most, all clients together: 32 status replies cost
#: about 0.3 ms from the per-cycle cache (benchmarks/robustness/flood.py), a few % of a 100 Hz period.
MAX_PER_CYCLE = 32
#: Share of the period that control work may take per cycle (the rest is the loop's):
#: at 100 Hz, 2.5 ms, ten uncached status replies (0.28 ms each, measured).
BUDGET_FRACTION = 0.25
#: No request starts with less than this left of the budget (s): twice an uncached status
#: reply; a costlier request (reload: re-reads files) overruns it, and is rare.
RESERVE_S = 0.5e-3
#: Requests taken off the socket and held, all clients together; beyond it they wait in
#: ZeroMQ's queues (ZMQ_RCVHWM), whose back-pressure slows the senders.
MAX_WAITING = 256


@dataclass
class Budget:
    """What one cycle may still spend on control requests: a count and seconds
    (measured with ``time.perf_counter``, real time whatever the loop's clock)."""

    requests: int = MAX_PER_CYCLE
    seconds: float = float("inf")
    served: int = 0

    def allows(self, reserve_s: float = 0.0) -> bool:
        # One request a cycle whatever the time left: on a machine too loaded to keep the
        # rate, `status` must still answer (a cached one costs about 15 us).
        return self.served == 0 and self.requests > 0 or self.requests > 0 and self.seconds > reserve_s

    def spend(self, seconds: float) -> None:
        self.requests -= 1
        self.seconds -= seconds
        self.served += 1


class Controlled(Protocol):
    """What the control requests act on (the daemon)."""

    @property
    def sensor_names(self) -> list[str]: ...

    def status(self) -> dict[str, Any]: ...

    def request_tare(self, envelope: list[bytes], sensors: list[str], samples: int) -> None: ...

    def untare(self, sensors: list[str]) -> dict[str, Any]: ...

    def request_reload(self, envelope: list[bytes] | None) -> dict[str, Any] | None: ...

    def set_loop(self, rate_hz: float, averaging: int, lowpass_hz: float) -> dict[str, Any]: ...

    def loop_settings(self) -> tuple[float, int, float]: ...

    def set_estimator(self, estimator: str, sensor: str | None) -> dict[str, Any]: ...

    def set_accuracy(self, value: object, envelope: list[bytes] | None = None) -> dict[str, Any] | None: ...


class Control:
    """Answers control requests on ``socket`` (None: no endpoint) for ``target``."""

    def __init__(self, socket: zmq.Socket | None, target: Controlled):
        self.socket, self.target = socket, target
        # Requests taken off the socket, by client (the ROUTER identity), in turn order.
        self.waiting: dict[bytes, deque[tuple[list[bytes], bytes]]] = {}
        self.held = 0  # requests in self.waiting
        self.answered = 0
        self.dropped = 0  # replies not sent: the client's queue was full (it does not read) or it left
        self._status_reply: tuple[object, dict[str, Any], bytes] | None = None  # (cycle key, reply, its JSON)
        self._changes = 0  # requests other than status handled: each may change the status

    def serve_waiting(self, budget: Budget | None = None) -> bool:
        """Answer waiting requests within ``budget`` (None: MAX_PER_CYCLE of them, no time
        limit), one per client per turn; the rest wait for the next call. Returns whether
        the budget is spent (the caller then leaves the socket alone until the next cycle)."""
        if self.socket is None:
            return False
        budget = budget or Budget()
        self._take()
        while self.waiting and budget.allows(RESERVE_S):
            client = next(iter(self.waiting))
            queue = self.waiting.pop(client)
            envelope, raw = queue.popleft()
            self.held -= 1
            if queue:
                self.waiting[client] = queue  # to the back of the turn order
            t0 = time.perf_counter()
            reply = self.handle(raw, envelope)
            if reply is not None:
                self.reply(envelope, reply)
            spent = time.perf_counter() - t0
            budget.spend(spent)
            self.answered += 1
            if not self.waiting:
                self._take()
        return not budget.allows(RESERVE_S)

    def _take(self) -> None:
        """Move what the socket holds into the clients' queues, MAX_WAITING in all (ZeroMQ
        reads its peers in turn, so a greedy client cannot take every place)."""
        assert self.socket is not None
        while self.held < MAX_WAITING:
            try:
                frames = self.socket.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                return
            if len(frames) < 2:
                continue  # not from a REQ or DEALER peer: nothing to answer to
            envelope, raw = frames[:-1], frames[-1]
            self.waiting.setdefault(envelope[0], deque()).append((envelope, raw))
            self.held += 1

    def reply(self, envelope: list[bytes], reply: dict[str, Any]) -> None:
        if self.socket is None:
            return
        cached = self._status_reply
        try:
            encoded = (
                cached[2]
                if cached is not None and reply is cached[1]
                else json.dumps(reply, default=float).encode()
            )
        except (TypeError, ValueError, RecursionError):  # a result JSON cannot hold: a bug, not an exit
            log.exception("control reply could not be encoded")
            encoded = b'{"ok": false, "error": "internal error (logged by the daemon)"}'
        try:
            self.socket.send_multipart([*envelope, encoded], zmq.NOBLOCK)
        except zmq.ZMQError:
            # Its queue full (EAGAIN: ZMQ_SNDHWM replies unread) or the peer gone
            # (EHOSTUNREACH, with ZMQ_ROUTER_MANDATORY): dropped, counted in `status`.
            self.dropped += 1

    def _cycle_key(self) -> object:
        """What the status depends on beyond this process's requests: the cycles run
        (None: unknown, no caching)."""
        cycles = getattr(getattr(self.target, "timing", None), "cycles", None)
        return None if not isinstance(cycles, int) else (cycles, self._changes)

    def handle(self, raw: bytes, envelope: list[bytes]) -> dict[str, Any] | None:
        """One JSON request; returns the reply, or None when it comes later (tare).
        Never raises: whatever ``raw`` holds, the answer is a reply."""
        try:
            request = parse_json(raw, max_bytes=MAX_REQUEST, max_depth=MAX_REQUEST_DEPTH)
        except ValueError as exc:
            return {"ok": False, "error": f"the request is not JSON within the limits: {str(exc)[:200]}"}
        if not isinstance(request, dict) or not isinstance(request.get("cmd"), str):
            return {"ok": False, "error": 'expected a JSON object with a string "cmd"'}
        handler = {
            "status": self._status,
            "tare": self._tare,
            "untare": self._untare,
            "reload": self._reload,
            "set": self._set,
        }.get(request["cmd"])
        if handler is None:
            return {
                "ok": False,
                "error": f"unknown command {request['cmd'][:40]!r}; commands: {', '.join(COMMANDS)}",
            }
        args = {k: v for k, v in request.items() if k != "cmd"}
        if request["cmd"] == "status" and not args:
            key = self._cycle_key()
            if key is not None and self._status_reply is not None and self._status_reply[0] == key:
                return self._status_reply[1]  # built this cycle already: reply encoded once
        else:
            self._changes += 1
        try:
            result = handler(args, envelope)
        except (FtsensordError, ValueError, TypeError) as exc:
            return {"ok": False, "error": str(exc)}
        except Exception:  # a bug must not stop the loop: log it, answer, go on
            log.exception("control request %r failed", request.get("cmd"))
            return {"ok": False, "error": "internal error (logged by the daemon)"}
        if result is None:
            return None
        reply = {"ok": True, "result": result}
        if request["cmd"] == "status" and not args:
            key = self._cycle_key()
            if key is not None:
                try:
                    self._status_reply = (key, reply, json.dumps(reply, default=float).encode())
                except (TypeError, ValueError):
                    log.exception("status reply could not be encoded")  # reply() answers the error
        return reply

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
        sensors = (
            [self._sensor(args["sensor"])] if args.get("sensor") is not None else self.target.sensor_names
        )
        self.target.request_tare(envelope, sensors, samples)
        return None

    def _untare(self, args: dict[str, Any], envelope: list[bytes]) -> dict[str, Any]:
        self._only(args, {"sensor"})
        sensors = (
            [self._sensor(args["sensor"])] if args.get("sensor") is not None else self.target.sensor_names
        )
        return self.target.untare(sensors)

    def _reload(self, args: dict[str, Any], envelope: list[bytes]) -> dict[str, Any] | None:
        self._only(args, set())
        return self.target.request_reload(envelope)

    def _set(self, args: dict[str, Any], envelope: list[bytes]) -> dict[str, Any] | None:
        self._only(args, {"rate_hz", "averaging", "lowpass_hz", "estimator", "sensor", "accuracy"})
        if "accuracy" in args:
            if set(args) != {"accuracy"}:
                raise ValueError(
                    "accuracy: set it in a request of its own (it chooses the rate, averaging and low-pass)"
                )
            return self.target.set_accuracy(args["accuracy"], envelope)  # None: answered when planned
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
        # Pings follow completed cycles only: a period longer than the watchdog allows is refused.
        check_watchdog = getattr(getattr(self.target, "notifier", None), "check_rate", None)
        if callable(check_watchdog):
            check_watchdog(float(rate))
        if not isinstance(averaging, int) or isinstance(averaging, bool) or not 1 <= averaging <= 10_000:
            raise ValueError("averaging: expected an integer from 1 to 10000")
        if not isinstance(lowpass, (int, float)) or isinstance(lowpass, bool) or not 0 <= lowpass < rate / 2:
            raise ValueError(
                f"lowpass_hz: expected a number from 0 (off) to below half the rate ({rate / 2:g})"
            )
        return self.target.set_loop(float(rate), averaging, float(lowpass))
