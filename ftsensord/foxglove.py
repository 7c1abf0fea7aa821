"""`ftsensord bridge`: the streams live in Foxglove, through a Foxglove WebSocket server.

Why Foxglove's live server rather than PlotJuggler's ZeroMQ source: the live server
carries the very messages `ftsensord record` writes to MCAP (ROS 2 ``WrenchStamped`` in
the stream's frame, ``MagneticField`` per chip, the ``SampleStatus`` companion with seq
and flags; `recording.ros2mcap.ros2_messages`), so one Foxglove layout serves a live
sensor and a recording alike; its protocol is documented and versioned, and a test can
speak it; the server is one maintained package (``foxglove-sdk``: the ``live`` extra).

Each sample is logged with ``log_time`` = its ``t_wall`` (ns), the same stamp as in its
header: a viewer shows it at the sample's time, not at arrival. The bridge is a client of
the daemon like any other (a `Subscriber`): a slow viewer slows the bridge, never the daemon.

The SDK's server speaks the WebSocket subprotocol ``foxglove.sdk.v1`` only: a viewer offering
just the protocol's older name, ``foxglove.websocket.v1`` (older Foxglove and Lichtblick
releases), is refused with HTTP 400 (docs/guide/clients.md, Bridges to live viewers).
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from ftsensord.errors import ConfigError

if (
    TYPE_CHECKING
):  # the command line (`cli.parser`) imports this module for its parser: nothing heavy until it runs
    from ftsensord.protocol import wire


#: What a failed handshake means, added to the server's own log line ("handshake failed").
HANDSHAKE_HINT = (
    "a viewer must offer the WebSocket subprotocol foxglove.sdk.v1; older Foxglove app and "
    "Lichtblick releases offer only foxglove.websocket.v1 and get HTTP 400: update the viewer "
    "(docs/guide/clients.md, Bridges to live viewers)"
)


class _HandshakeHint(logging.Filter):
    """Says why, where the SDK's server logs only that a client's handshake failed."""

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        if "handshake failed" in message:
            record.msg, record.args = f"{message}: {HANDSHAKE_HINT}", ()
        return True


class FoxgloveSink:
    """Samples to a Foxglove WebSocket server, one channel per ROS 2 topic (a `recording.SampleWriter`)."""

    def __init__(self, frames: dict[str, str], host: str = "127.0.0.1", port: int = 8765):
        try:
            import foxglove
        except ImportError as exc:
            raise ConfigError(
                "the Foxglove bridge needs the foxglove-sdk package: pip install 'ftsensord[live]'"
            ) from exc
        from ftsensord.recording.ros2mcap import SCHEMAS, ros2_messages

        self._foxglove, self._messages = foxglove, ros2_messages
        server_log = logging.getLogger("foxglove.websocket.server")
        if not any(isinstance(f, _HandshakeHint) for f in server_log.filters):
            server_log.addFilter(_HandshakeHint())
        self.frames = frames
        self.server = foxglove.start_server(name="ftsensord", host=host, port=port)
        self.port: int = self.server.port
        self.schemas = {
            name: foxglove.Schema(name=name, encoding="ros2msg", data=text.encode())
            for name, text in SCHEMAS.items()
        }
        self.channels: dict[str, Any] = {}
        self.last_seq: dict[str, int] = {}
        self.file = None  # no file: a write that fails names none (`recording.SampleWriter`)

    def write(self, sample: wire.Sample) -> None:
        last = self.last_seq.get(sample.topic)
        self.last_seq[sample.topic] = sample.seq
        t_ns = round(sample.t_wall * 1e9)
        for topic, schema, _frame, data in self._messages(
            sample, self.frames.get(sample.topic, sample.topic), last
        ):
            channel = self.channels.get(topic)
            if channel is None:
                channel = self.channels[topic] = self._foxglove.Channel(
                    topic, message_encoding="cdr", schema=self.schemas[schema]
                )
            channel.log(data, log_time=t_ns)

    def flush(self) -> None:
        pass  # sent as logged

    def close(self, tallies: Mapping[str, Any]) -> None:
        self.server.stop()


def cmd_bridge(args: argparse.Namespace) -> int:
    from ftsensord.client import Subscriber
    from ftsensord.recording import StopOnSignals, daemon_frames, record, summary_line

    with StopOnSignals() as stopped:
        frames = daemon_frames(args.streams, args.endpoint, args.control, args.timeout)
        sink = FoxgloveSink(frames, args.host, args.port)
        print(
            f"ftsensord: Foxglove live server on ws://{args.host}:{sink.port} "
            f"({', '.join(args.streams)}); Ctrl-C stops it",
            flush=True,
        )
        with Subscriber(args.endpoint, args.streams) as sub:
            outcome = record(
                sub, sink, args.streams, seconds=args.seconds, timeout_s=math.inf, stop=stopped.is_set
            )
    print(
        summary_line(f"ws://{args.host}:{sink.port}", outcome, stopped.name, verb="served"), file=sys.stderr
    )
    return 0


def add_parser(sub: Any) -> None:
    """The ``bridge`` command (`cli.parser` calls this)."""
    p = sub.add_parser(
        "bridge",
        help="serve streams live to Foxglove (a Foxglove WebSocket server)",
        description="The streams as ROS 2 messages, as `record` writes them to MCAP, on a "
        "Foxglove WebSocket server: open ws://HOST:PORT in Foxglove. "
        "docs/guide/clients.md, Bridges to live viewers.",
    )
    p.add_argument(
        "streams", nargs="+", metavar="STREAM", help="wrench/<sensor>, wrench/tip, flux/<sensor>, ..."
    )
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1: this host)")
    p.add_argument("--port", type=int, default=8765, help="port (default 8765, Foxglove's; 0: any free one)")
    p.add_argument("--seconds", type=float, help="stop after this long (default: until Ctrl-C or SIGTERM)")
    p.add_argument("--endpoint", help="publish endpoint (default: the running daemon's ipc socket)")
    p.add_argument("--control", help="control endpoint, asked for the frames (default: beside --endpoint)")
    p.add_argument("--timeout", type=float, default=3.0, help="how long to wait for the daemon's frames")
    p.set_defaults(func=cmd_bridge)
