"""The ``ftsensord`` command line.

``main(argv) -> int`` is what the console script runs and what tests call.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence

from ftsensord import __version__
from ftsensord.acquire.bus import ACCEPTED_FORMS, open_bus
from ftsensord.acquire.scan import format_table, scan
from ftsensord.foxglove import add_parser as add_bridge_parser
from ftsensord.ros2 import InLoop, add_ros2_parser
from ftsensord.errors import ConfigError, DaemonNotAnswering, FtsensordError
from ftsensord.config.sensors import ESTIMATORS
from ftsensord.daemon.status import describe
from ftsensord.sim.loads import HOLD_PERIOD_S, HOLD_S, PLANS


def cmd_scan(args: argparse.Namespace) -> int:
    bus = open_bus(args.bus, exclusive=True, force=args.force)  # it reconfigures chips: never under a daemon
    try:
        reports = scan(bus)
    finally:
        bus.close()
    if args.json:
        print(json.dumps({"bus": args.bus, "chips": [r.as_dict() for r in reports]}, indent=2))
    else:
        print(format_table(reports, args.bus))
    if not reports:
        print(f"no MLX90393 answered on {args.bus} (0x0C-0x1B)", file=sys.stderr)
        return 1
    return 2 if any(r.error for r in reports) else 0


def _rate_hz(text: str) -> float:
    """An argparse type: a finite rate above 0 Hz."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a positive number of Hz, got {text!r}")
    return value


def cmd_doctor(args: argparse.Namespace) -> int:
    from ftsensord.acquire.bound import SCHEDULERS
    from ftsensord.acquire.doctor import doctor, format_doctor

    report = doctor(args.bus, (args.scheduler,) if args.scheduler else SCHEDULERS, bus_hz=args.bus_hz,
                    force=args.force, real_time=args.real_time, rate_hz=args.rate)
    print(json.dumps(report, indent=2) if args.json else format_doctor(report))
    if not report["chips"]:
        print(f"no MLX90393 answered on {args.bus} (0x0C-0x1B)", file=sys.stderr)
        return 1
    return 2 if report["warnings"] or any(c["error"] for c in report["chips"]) else 0


def cmd_dataset(args: argparse.Namespace) -> int:
    from ftsensord.calibration.procedure import simulate_dataset

    sizes = {k: getattr(args, k) for k in ("poses", "validation_poses", "samples", "seed", "no_load_poses",
                                           "check_poses", "hold_s", "hold_period_s")}
    dataset = simulate_dataset(args.scene, args.sensor, args.plan, sweeps=not args.no_sweep, **sizes)
    dataset.save(args.output)
    print(f"wrote {args.output}: {len(dataset)} poses ({args.plan}), {args.samples} samples each, "
          f"{int(dataset.saturated.any(axis=1).sum())} with a saturated chip" + (
              f"; a step-and-hold of {len(dataset.hold.times_s)} readings" if dataset.hold is not None else ""))
    return 0


def cmd_calibrate(args: argparse.Namespace) -> int:
    from ftsensord.calibration.dataset import Dataset
    from ftsensord.calibration.nlfit import FitProgress
    from ftsensord.calibration.procedure import calibrate, summary
    from ftsensord.calibration.report import write_report
    from ftsensord.errors import CalibrationError

    dataset = Dataset.load(args.dataset)

    def progress(p: FitProgress) -> None:
        print(f"nonlinear fit: iteration {p.step}/{p.steps}, residual {p.rms_residual_t * 1e6:.2f} uT RMS, "
              f"{p.elapsed_s:.1f} s", file=sys.stderr, flush=True)

    try:
        cal, result = calibrate(dataset, serial=args.serial, frame=args.frame, nonlinear=not args.linear_only,
                                progress=progress, allow_poor_fit=args.allow_poor_fit)
    except CalibrationError as exc:
        if "nonlinear fit is refused" not in str(exc):
            raise
        # Nothing is written: the user chooses between the linear part alone and a poor fit.
        raise CalibrationError(f"{exc}\nNo file written. To write the linear calibration alone: "
                               f"ftsensord calibrate {args.dataset} -o {args.output} --linear-only; to keep "
                               "this nonlinear fit with its warnings: add --allow-poor-fit") from exc
    cal.save(args.output)
    print(summary(cal))
    print(f"wrote {args.output}")
    if args.report:
        command = "ftsensord calibrate " + " ".join(args.argv)
        write_report(args.report, result.model, cal.report, dataset.select(dataset.split == "validation"), command)
        print(f"wrote {args.report}")
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    import logging
    from ftsensord.config.file import load_config
    from ftsensord.daemon.run import run
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    return run(load_config(args.config), early=args.early_signals, realtime=args.realtime, ros2_in_loop=InLoop)


def _control(args: argparse.Namespace):
    from ftsensord.client import ControlClient
    curve = (args.curve_cert, args.server_cert) if args.curve_cert else None
    if (args.curve_cert is None) != (args.server_cert is None):
        raise ConfigError("--curve-cert and --server-cert go together (CURVE needs both)")
    return ControlClient(args.control, timeout_s=args.timeout, curve=curve)


def cmd_status(args: argparse.Namespace) -> int:
    status = _control(args).status()
    print(json.dumps(status, indent=2) if args.json else describe(status))
    return 0


def cmd_tare(args: argparse.Namespace) -> int:
    result = _control(args).tare(samples=args.samples, sensor=args.sensor)
    for name, offset in result["tare_wrench"].items():
        print(f"{name}: tared on {result['samples']} samples; removed " + " ".join(f"{v:+.4g}" for v in offset)
              + " (N, N, N, Nm, Nm, Nm)")
    return 0


def cmd_untare(args: argparse.Namespace) -> int:
    result = _control(args).untare(sensor=args.sensor)
    for name, offset in result["removed_tare_wrench"].items():
        print(f"{name}: back to the calibration's zero; the tare had removed "
              + " ".join(f"{v:+.4g}" for v in offset) + " (N, N, N, Nm, Nm, Nm)")
    return 0


def cmd_set(args: argparse.Namespace) -> int:
    changes = {k: v for k, v in (("rate_hz", args.rate), ("averaging", args.averaging),
                                 ("lowpass_hz", args.lowpass), ("estimator", args.estimator)) if v is not None}
    if not changes:
        raise ConfigError("set: nothing to change; give --rate, --averaging, --lowpass or --estimator")
    if args.sensor and set(changes) != {"estimator"}:
        raise ConfigError("set: --sensor goes with --estimator only (rate, averaging and low-pass are the loop's)")
    control = _control(args)
    if "estimator" in changes:  # its own request: it is per sensor, the others are the loop's
        sensor = {"sensor": args.sensor} if args.sensor else {}
        result = control.set(estimator=changes.pop("estimator"), **sensor)
        print("estimator: " + ", ".join(f"{n} {e}" for n, e in result["estimator"].items()))
    if changes:
        result = control.set(**changes)
        print(f"rate {result['rate_hz']:g} Hz, averaging {result['averaging']}, "
              f"low-pass {result['lowpass_hz'] or 'off'}")
    return 0


def cmd_reload(args: argparse.Namespace) -> int:
    result = _control(args).reload()
    print(f"reloaded {result['config']}; calibrations: "
          + ", ".join(f"{name} {path}" for name, path in result["calibrations"].items()))
    return 0


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
            outcome = record(sub, writer, args.streams, count=args.count, seconds=args.seconds,
                             timeout_s=args.timeout, stop=stopped.is_set)
    if outcome.reason == "timeout":
        print(f"ftsensord: no sample within {args.timeout:g} s", file=sys.stderr)
    print(summary_line(args.file, outcome, stopped.name), flush=True)
    return 0 if any(t.samples for t in outcome.tallies.values()) else 1


def cmd_plot(args: argparse.Namespace) -> int:
    from ftsensord.client import check_streams
    from ftsensord.plot import live, snapshot

    check_streams(args.streams, args.endpoint, args.control, timeout_s=min(args.timeout, 1.0))
    if args.png:
        shot = snapshot(args.streams, args.seconds or 5.0, args.png, endpoint=args.endpoint, timeout_s=args.timeout)
        print(f"wrote {args.png}: " + ", ".join(f"{s} {h.samples} samples, {h.missed} missed"
                                                for s, h in shot.histories.items()))
        return 0 if all(h.samples for h in shot.histories.values()) else 1
    return live(args.streams, args.seconds or 10.0, endpoint=args.endpoint)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="ftsensord", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"ftsensord {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("run", help="run the daemon (the systemd unit runs this)",
                       description="Read every chip in a steady loop, publish wrenches over ZeroMQ, and "
                                   "serve control requests. SIGTERM stops it cleanly, SIGHUP reloads.")
    p.add_argument("--config", help="configuration file (default: the simulated bus, default scene)")
    p.add_argument("--realtime", type=int, default=0, metavar="PRIORITY", help="ask for SCHED_FIFO at this "
                   "priority, 1-99 (the unit: 50); refused, it says why and runs as usual (default 0: not asked)")
    p.set_defaults(func=cmd_run)

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

    p = sub.add_parser("status", help="the running daemon's health",
                       description="Rate achieved against configured and the computed bound, jitter, "
                                   "missed cycles, per-chip errors and temperatures, tare offsets, "
                                   "calibrations. Exit 1 with a message when no daemon answers.")
    p.add_argument("--json", action="store_true", help="print the whole status as JSON")
    control_options(p)
    p.set_defaults(func=cmd_status)

    p = sub.add_parser("tare", help="zero the output at the present load")
    p.add_argument("--samples", type=int, default=100, help="cycles to average (default 100)")
    p.add_argument("--sensor", help="only this sensor (default: all)")
    control_options(p)
    p.set_defaults(func=cmd_tare)

    p = sub.add_parser("untare", help="undo the tare: back to the calibration's own zero")
    p.add_argument("--sensor", help="only this sensor (default: all)")
    control_options(p)
    p.set_defaults(func=cmd_untare)

    p = sub.add_parser("set", help="change the rate, averaging, low-pass or estimator of the running daemon",
                       description="Changes last until the next restart or reload; a rate above the "
                                   "computed bound is refused, and nothing changes.")
    p.add_argument("--rate", type=_rate_hz, help="loop rate, Hz")
    p.add_argument("--averaging", type=int, help="samples in the moving average (1: off)")
    p.add_argument("--lowpass", type=float, help="first-order low-pass cutoff, Hz (0: off)")
    p.add_argument("--estimator", choices=ESTIMATORS, help="K A, or the flux model (docs/design/estimators.md)")
    p.add_argument("--sensor", help="with --estimator: only this sensor (default: all)")
    control_options(p)
    p.set_defaults(func=cmd_set)

    p = sub.add_parser("reload", help="re-read the configuration and calibration files (as SIGHUP does)",
                       description="A file with an error is refused with a message naming the file and key; "
                                   "the running configuration then stays.")
    control_options(p)
    p.set_defaults(func=cmd_reload)

    p = sub.add_parser("echo", help="print a stream's samples live")
    stream_options(p)
    p.set_defaults(func=cmd_echo)

    p = sub.add_parser("record", help="record streams to CSV, NPZ or MCAP (by the file's extension)",
                       description="Written as it arrives; Ctrl-C, SIGTERM or SIGHUP end it with the file "
                                   "complete and a summary. docs/guide/clients.md, Recording.")
    p.add_argument("streams", nargs="+", metavar="STREAM", help="wrench/<sensor>, wrench/tip or flux/<sensor>")
    p.add_argument("file", help="output file: .csv, .npz or .mcap")
    p.add_argument("--endpoint", help="publish endpoint (default: the running daemon's ipc socket)")
    p.add_argument("--control", help="control endpoint, asked for the frames (default: beside --endpoint)")
    p.add_argument("--count", type=int, help="stop after this many samples (all streams together)")
    p.add_argument("--seconds", type=float, help="stop after this long")
    p.add_argument("--timeout", type=float, default=3.0, help="give up after this long without a sample")
    p.set_defaults(func=cmd_record)

    p = sub.add_parser("plot", help="live plot of streams' wrenches and flags (or, --png, a snapshot)")
    p.add_argument("streams", nargs="+", metavar="STREAM", help="wrench/<sensor>, wrench/tip or flux/<sensor>")
    p.add_argument("--seconds", type=float, help="time shown (default 10; with --png: collected, default 5)")
    p.add_argument("--png", help="write a snapshot to this file and exit (headless)")
    p.add_argument("--endpoint", help="publish endpoint (default: the running daemon's ipc socket)")
    p.add_argument("--control", help="control endpoint, asked for the streams (default: beside --endpoint)")
    p.add_argument("--timeout", type=float, default=3.0, help="with --png: give up after this long without a sample")
    p.set_defaults(func=cmd_plot)

    add_bridge_parser(sub)
    add_ros2_parser(sub)
    p = sub.add_parser("scan", help="find MLX90393 chips on a bus and read each once",
                       description="Probe 0x0C-0x1B and print each chip's part variant, "
                                   "configuration registers (as found) and one reading. "
                                   "Stops and reconfigures the chips: takes the bus's lock and refuses a bus "
                                   "a running daemon holds unless --force. "
                                   "Exit 0: all read; 1: none found; 2: some failed.")
    p.add_argument("--bus", default="sim", help=f"bus to scan: {ACCEPTED_FORMS} (default: sim)")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.add_argument("--force", action="store_true", help="go on when another process (a daemon) holds the bus")
    p.set_defaults(func=cmd_scan)

    p = sub.add_parser("doctor", help="bring a board up: adapter, clock, ioctl cost, chips, bound and rate",
                       description="Name the I2C adapter and what it accepts in one ioctl, the configured and "
                                   "measured clock and the cost of one ioctl; find the chips, read each and count "
                                   "errors over 300 register reads; per scheduler, the computed bound for the "
                                   "chips found and the rate measured running at it. Takes the bus's lock: "
                                   "refuses a bus a running daemon holds unless --force. Exit 0: all well; "
                                   "1: no chip; 2: a warning or a failing chip.")
    p.add_argument("--bus", default="sim", help=f"bus: {ACCEPTED_FORMS} (default: sim)")
    p.add_argument("--scheduler", choices=("naive", "overlapped", "burst"), help="only this scheduler (default: all)")
    p.add_argument("--bus-hz", type=float, default=400e3, help="the clock ftsensord is configured with, Hz (default 400000)")
    p.add_argument("--rate", type=_rate_hz, default=100.0, help="the rate `run` would choose for, Hz (default 100)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--force", action="store_true", help="go on when another process (a daemon) holds the bus")
    p.add_argument("--real-time", action="store_true",
                   help="on the simulated bus, spend real time (default: its virtual clock, instant)")
    p.set_defaults(func=cmd_doctor)

    p = sub.add_parser("dataset", help="record a calibration dataset on the simulated bus",
                       description="Run the paper's calibration procedure (section VII-B) on a simulated "
                                   "sensor: for each pose of the plan, apply the weight's wrench and average "
                                   "the chips' readings; also simulate each chip's position-map sweep. The "
                                   "file has the format a real calibration run records "
                                   "(docs/guide/calibration.md).")
    p.add_argument("-o", "--output", required=True, help="dataset file to write (JSON)")
    p.add_argument("--scene", help="scene file of kind \"sensors\" (default: two as-built sensors in the room)")
    p.add_argument("--sensor", default="sensor1", help="which sensor of the scene (default: sensor1)")
    p.add_argument("--plan", default="six-axis", choices=sorted(PLANS),
                   help="lever arms: four that excite all six axes (default), or the paper's single rod")
    p.add_argument("--poses", type=int, default=193, help="fit poses, 50 g and 200 g (default: 193)")
    p.add_argument("--validation-poses", type=int, default=60, help="validation poses, 100 g (default: 60)")
    p.add_argument("--samples", type=int, default=100, help="readings averaged per pose (default: 100)")
    p.add_argument("--seed", type=int, default=0, help="noise seed (default: 0)")
    p.add_argument("--no-sweep", action="store_true", help="leave out the position-map sweeps")
    p.add_argument("--no-load-poses", type=int, default=24,
                   help="poses with the rod and masses off, to measure the room's field (default: 24; "
                        "at least 6 for the fit to use them, 12 or more advised)")
    p.add_argument("--check-poses", type=int, default=24, help="poses with 1, 2 and 4 kg at the flange's centre, "
                   "on which the model is judged at large loads (default: 24; 0: none)")
    p.add_argument("--hold-s", type=float, default=HOLD_S, help="s each step-and-hold pose is held "
                   "(0: none; docs/guide/calibration.md)")
    p.add_argument("--hold-period-s", type=float, default=HOLD_PERIOD_S, help="s between its readings (0: fastest)")
    p.set_defaults(func=cmd_dataset)

    p = sub.add_parser("calibrate", help="fit K, A and the zero from a dataset",
                       description="Fit w = K A (b - b0) to the dataset's fit poses, report the validation "
                                   "RMSE per axis and write the calibration file. Refuses (exit 2), naming the "
                                   "cause and the fix, data it can tell are wrong; leaves out outlier and repeated "
                                   "poses, and keeps a weak plan or a part off the model, with a WARNING line each.")
    p.add_argument("dataset", help="dataset file (from `ftsensord dataset` or a real calibration run)")
    p.add_argument("-o", "--output", required=True, help="calibration file to write (JSON)")
    p.add_argument("--report", help="also write a Markdown report (and a PNG plot beside it)")
    p.add_argument("--serial", help="sensor serial to record (default: the dataset's)")
    p.add_argument("--frame", default="sensor", help="name of the sensor frame (default: sensor)")
    p.add_argument("--linear-only", action="store_true",
                   help="skip the nonlinear estimator's calibration (a few s for 193 poses)")
    p.add_argument("--allow-poor-fit", action="store_true",
                   help="keep a nonlinear fit that would be refused (a magnet fitted far off, a residual far "
                        "above noise), with its warnings in the file and report")
    p.set_defaults(func=cmd_calibrate)
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
