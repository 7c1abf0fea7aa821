"""What several commands share: the rate's type, the options of a control client and of a
stream, the control client itself."""

from __future__ import annotations

import argparse
import math
from typing import TYPE_CHECKING

from ftsensord.errors import ConfigError

if TYPE_CHECKING:  # imported when a command asks the daemon: `dataset` needs no ZeroMQ
    from ftsensord.client import ControlClient


def rate_hz(text: str) -> float:
    """An argparse type: a finite rate above 0 Hz."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a positive number of Hz, got {text!r}")
    return value


def control_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--control", help="control endpoint (default: the running daemon's ipc socket)")
    p.add_argument("--timeout", type=float, default=3.0, help="seconds to wait for the daemon (default 3)")
    p.add_argument("--curve-cert", help="this client's certificate (with secret key), for a CURVE endpoint")
    p.add_argument("--server-cert", help="the daemon's public certificate, for a CURVE endpoint")


def stream_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("stream", help="stream: wrench/<sensor>, wrench/tip or flux/<sensor>")
    p.add_argument("--endpoint", help="publish endpoint (default: the running daemon's ipc socket)")
    p.add_argument("--control", help="control endpoint, asked for the streams (default: beside --endpoint)")
    p.add_argument("--count", type=int, help="stop after this many samples")
    p.add_argument("--timeout", type=float, default=3.0, help="give up after this long without a sample")


def control_client(args: argparse.Namespace) -> ControlClient:
    from ftsensord.client import ControlClient

    curve = (args.curve_cert, args.server_cert) if args.curve_cert else None
    if (args.curve_cert is None) != (args.server_cert is None):
        raise ConfigError("--curve-cert and --server-cert go together (CURVE needs both)")
    return ControlClient(args.control, timeout_s=args.timeout, curve=curve)
