"""The commands that take the daemon's streams: echo, record, plot (the Foxglove bridge and the
ROS 2 output add their own, `foxglove.add_parser` and `ros2.add_ros2_parser`)."""

from __future__ import annotations

import argparse
import sys

from ftsensord.cli.options import stream_options


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Its commands, in the order `ftsensord --help` lists them."""
    p = sub.add_parser("echo", help="print a stream's samples live")
    stream_options(p)
    p.set_defaults(func=cmd_echo)
    p = sub.add_parser(
        "record",
        help="record streams to CSV, NPZ or MCAP (by the file's extension)",
        description="Written as it arrives; Ctrl-C, SIGTERM or SIGHUP end it with the file "
        "complete and a summary. docs/guide/clients.md, Recording.",
    )
    p.add_argument(
        "streams", nargs="+", metavar="STREAM", help="wrench/<sensor>, wrench/tip or flux/<sensor>"
    )
    p.add_argument("file", help="output file: .csv, .npz or .mcap")
    p.add_argument("--endpoint", help="publish endpoint (default: the running daemon's ipc socket)")
    p.add_argument("--control", help="control endpoint, asked for the frames (default: beside --endpoint)")
    p.add_argument("--count", type=int, help="stop after this many samples (all streams together)")
    p.add_argument("--seconds", type=float, help="stop after this long")
    p.add_argument("--timeout", type=float, default=3.0, help="give up after this long without a sample")
    p.set_defaults(func=cmd_record)
    p = sub.add_parser("plot", help="live plot of streams' wrenches and flags (or, --png, a snapshot)")
    p.add_argument(
        "streams", nargs="+", metavar="STREAM", help="wrench/<sensor>, wrench/tip or flux/<sensor>"
    )
    p.add_argument("--seconds", type=float, help="time shown (default 10; with --png: collected, default 5)")
    p.add_argument("--png", help="write a snapshot to this file and exit (headless)")
    p.add_argument("--endpoint", help="publish endpoint (default: the running daemon's ipc socket)")
    p.add_argument("--control", help="control endpoint, asked for the streams (default: beside --endpoint)")
    p.add_argument(
        "--timeout", type=float, default=3.0, help="with --png: give up after this long without a sample"
    )
    p.set_defaults(func=cmd_plot)


def cmd_echo(args: argparse.Namespace) -> int:
    from ftsensord.echo import echo

    return echo(args.stream, args.endpoint, args.control, args.count, args.timeout)


def cmd_record(args: argparse.Namespace) -> int:
    from ftsensord.client import Subscriber
    from ftsensord.recording import StopOnSignals, daemon_frames, open_writer, record, summary_line

    with StopOnSignals() as stopped:  # from here on a signal ends the recording cleanly
        frames = daemon_frames(args.streams, args.endpoint, args.control, args.timeout)
        with Subscriber(args.endpoint, args.streams) as sub:  # a bad endpoint: refused before a file is made
            writer = open_writer(args.file, args.streams, frames)
            outcome = record(
                sub,
                writer,
                args.streams,
                count=args.count,
                seconds=args.seconds,
                timeout_s=args.timeout,
                stop=stopped.is_set,
            )
    if outcome.reason == "timeout":
        print(f"ftsensord: no sample within {args.timeout:g} s", file=sys.stderr)
    print(summary_line(args.file, outcome, stopped.name), flush=True)
    return 0 if any(t.samples for t in outcome.tallies.values()) else 1


def cmd_plot(args: argparse.Namespace) -> int:
    from ftsensord.client import check_streams
    from ftsensord.plot import live, snapshot

    check_streams(args.streams, args.endpoint, args.control, timeout_s=min(args.timeout, 1.0))
    if args.png:
        shot = snapshot(
            args.streams, args.seconds or 5.0, args.png, endpoint=args.endpoint, timeout_s=args.timeout
        )
        print(
            f"wrote {args.png}: "
            + ", ".join(f"{s} {h.samples} samples, {h.missed} missed" for s, h in shot.histories.items())
        )
        return 0 if all(h.samples for h in shot.histories.values()) else 1
    return live(args.streams, args.seconds or 10.0, endpoint=args.endpoint)
