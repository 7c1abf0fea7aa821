"""The ``ftsensord`` command line: the parser, its command groups in the order `--help` lists
them, and ``main(argv) -> int``, what the console script runs and what tests call."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from ftsensord import __version__
from ftsensord.cli import calibrate, guide, hardware, service, streams
from ftsensord.errors import DaemonNotAnswering, FtsensordError
from ftsensord.foxglove import add_parser as add_bridge_parser
from ftsensord.ros2 import add_ros2_parser


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="ftsensord", description="The ``ftsensord`` command line.")
    parser.add_argument("--version", action="version", version=f"ftsensord {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    service.add_parsers(sub)
    streams.add_parsers(sub)
    add_bridge_parser(sub)
    add_ros2_parser(sub)
    hardware.add_parsers(sub)
    calibrate.add_parsers(sub)
    guide.add_parsers(sub)
    return parser


def main(argv: Sequence[str] | None = None, early_signals: Sequence[int] = ()) -> int:
    """``early_signals``: what came before the handlers of `ftsensord run` (`__main__`)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    args.argv, args.early_signals = argv[1:], early_signals
    try:
        return int(args.func(args))
    except KeyboardInterrupt:  # Ctrl-C: a message, not a traceback
        print("ftsensord: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # The reader left (`ftsensord echo ... | head`) with what it wanted. As the Python docs
        # advise: point stdout at devnull, so the interpreter's last flush does not fail again.
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except DaemonNotAnswering as exc:
        print(f"ftsensord: {exc}", file=sys.stderr)
        return 1
    except FtsensordError as exc:
        print(f"ftsensord: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # e.g. /dev/i2c-N missing or not permitted
        print(f"ftsensord: {exc}", file=sys.stderr)
        return 2
