"""`ftsensord run` and the commands that ask the running daemon: status, tare, untare, set, reload."""

from __future__ import annotations

import argparse
import json

from ftsensord.cli.options import control_client, control_options, rate_hz
from ftsensord.config.accuracy import parse_accuracies
from ftsensord.config.sensors import ESTIMATORS
from ftsensord.daemon.status import describe
from ftsensord.errors import ConfigError
from ftsensord.ros2 import InLoop


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Its commands, in the order `ftsensord --help` lists them."""
    p = sub.add_parser(
        "run",
        help="run the daemon (the systemd unit runs this)",
        description="Read every chip in a steady loop, publish wrenches over ZeroMQ, and "
        "serve control requests. SIGTERM stops it cleanly, SIGHUP reloads.",
    )
    p.add_argument("--config", help="configuration file (default: the simulated bus, default scene)")
    p.add_argument(
        "--realtime",
        type=int,
        default=0,
        metavar="PRIORITY",
        help="ask for SCHED_FIFO at this "
        "priority, 1-99 (the unit: 50); refused, it says why and runs as usual (default 0: not asked)",
    )
    p.set_defaults(func=cmd_run)
    p = sub.add_parser(
        "status",
        help="the running daemon's health",
        description="Rate achieved against configured and the computed bound, jitter, "
        "missed cycles, per-chip errors and temperatures, tare offsets, "
        "calibrations. Exit 1 with a message when no daemon answers.",
    )
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
    p = sub.add_parser(
        "set",
        help="change the rate, averaging, low-pass or estimator of the running daemon, or ask for an accuracy",
        description="Changes last until the next restart or reload; a rate above the "
        "computed bound is refused, and nothing changes. --accuracy chooses the fastest chip "
        "conversion (OSR, DIG_FILT), rate and averaging (the low-pass off) whose predicted sigma "
        "at rest meets the target on every sensor at its estimator and tare, writes the "
        "conversion to the chips, and says the rate; or why none does. docs/reference/cli.md.",
    )
    p.add_argument("--rate", type=rate_hz, help="loop rate, Hz")
    p.add_argument("--averaging", type=int, help="samples in the moving average (1: off)")
    p.add_argument("--lowpass", type=float, help="first-order low-pass cutoff, Hz (0: off)")
    p.add_argument(
        "--estimator", choices=ESTIMATORS, help="K A, or the flux model (docs/design/estimators.md)"
    )
    p.add_argument("--sensor", help="with --estimator: only this sensor (default: all)")
    p.add_argument(
        "--accuracy",
        action="append",
        metavar="SIGMA",
        help="a 1-sigma every force axis (0.02N, 20mN) or torque axis (0.5mNm) must meet at rest; "
        "once for each kind; alone",
    )
    control_options(p)
    p.set_defaults(func=cmd_set)
    p = sub.add_parser(
        "reload",
        help="re-read the configuration and calibration files (as SIGHUP does)",
        description="A file with an error is refused with a message naming the file and key; "
        "the running configuration then stays.",
    )
    control_options(p)
    p.set_defaults(func=cmd_reload)


def cmd_run(args: argparse.Namespace) -> int:
    import logging

    from ftsensord.config.file import load_config
    from ftsensord.daemon.run import run

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    return run(
        load_config(args.config), early=args.early_signals, realtime=args.realtime, ros2_in_loop=InLoop
    )


def cmd_status(args: argparse.Namespace) -> int:
    status = control_client(args).status()
    print(json.dumps(status, indent=2) if args.json else describe(status))
    return 0


def cmd_tare(args: argparse.Namespace) -> int:
    result = control_client(args).tare(samples=args.samples, sensor=args.sensor)
    for name, offset in result["tare_wrench"].items():
        print(
            f"{name}: tared on {result['samples']} samples; removed "
            + " ".join(f"{v:+.4g}" for v in offset)
            + " (N, N, N, Nm, Nm, Nm)"
        )
    return 0


def cmd_untare(args: argparse.Namespace) -> int:
    result = control_client(args).untare(sensor=args.sensor)
    for name, offset in result["removed_tare_wrench"].items():
        print(
            f"{name}: back to the calibration's zero; the tare had removed "
            + " ".join(f"{v:+.4g}" for v in offset)
            + " (N, N, N, Nm, Nm, Nm)"
        )
    return 0


def cmd_set(args: argparse.Namespace) -> int:
    if args.accuracy:
        if any(v is not None for v in (args.rate, args.averaging, args.lowpass, args.estimator, args.sensor)):
            raise ConfigError("set: --accuracy goes alone (it chooses the rate, averaging and low-pass)")
        parse_accuracies(args.accuracy, "--accuracy")  # a typo said here, before the daemon is asked
        result = control_client(args).set(accuracy=args.accuracy)
        print(
            f"rate {result['rate_hz']:g} Hz, averaging {result['averaging']}, low-pass off: "
            f"{result['effective_rate_hz']:g} independent samples a second (OSR {result['osr']}, "
            f"DIG_FILT {result['dig_filt']}, "
            + ("the chips' conversion changed to it)" if result["conversion_changed"] else "as running)")
        )
        for name, sigma in result["sigma"].items():
            print(
                f"{name}: predicted sigma at rest "
                + " ".join(f"{v:.4g}" for v in sigma)
                + " (N, N, N, Nm, Nm, Nm)"
            )
        return 0
    changes = {
        k: v
        for k, v in (
            ("rate_hz", args.rate),
            ("averaging", args.averaging),
            ("lowpass_hz", args.lowpass),
            ("estimator", args.estimator),
        )
        if v is not None
    }
    if not changes:
        raise ConfigError("set: nothing to change; give --rate, --averaging, --lowpass or --estimator")
    if args.sensor and set(changes) != {"estimator"}:
        raise ConfigError(
            "set: --sensor goes with --estimator only (rate, averaging and low-pass are the loop's)"
        )
    control = control_client(args)
    if "estimator" in changes:  # its own request: it is per sensor, the others are the loop's
        sensor = {"sensor": args.sensor} if args.sensor else {}
        result = control.set(estimator=changes.pop("estimator"), **sensor)
        print("estimator: " + ", ".join(f"{n} {e}" for n, e in result["estimator"].items()))
    if changes:
        result = control.set(**changes)
        print(
            f"rate {result['rate_hz']:g} Hz, averaging {result['averaging']}, "
            f"low-pass {result['lowpass_hz'] or 'off'}"
        )
    return 0


def cmd_reload(args: argparse.Namespace) -> int:
    result = control_client(args).reload()
    print(
        f"reloaded {result['config']}; calibrations: "
        + ", ".join(f"{name} {path}" for name, path in result["calibrations"].items())
    )
    return 0
