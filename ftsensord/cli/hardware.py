"""The commands that bring a board up: scan and doctor. Both stop and reconfigure the chips they
find, so they take the bus's lock."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from ftsensord.acquire.bus import ACCEPTED_FORMS, open_bus
from ftsensord.acquire.scan import format_table, scan
from ftsensord.cli.options import rate_hz


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Its commands, in the order `ftsensord --help` lists them."""
    p = sub.add_parser(
        "scan",
        help="find MLX90393 chips on a bus and read each once",
        description="Probe 0x0C-0x1B and print each chip's part variant, "
        "configuration registers (as found) and one reading. "
        "Stops and reconfigures the chips: takes the bus's lock and refuses a bus "
        "a running daemon holds unless --force. "
        "Exit 0: all read; 1: none found; 2: some failed.",
    )
    p.add_argument("--bus", default="sim", help=f"bus to scan: {ACCEPTED_FORMS} (default: sim)")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.add_argument("--force", action="store_true", help="go on when another process (a daemon) holds the bus")
    p.set_defaults(func=cmd_scan)
    p = sub.add_parser(
        "doctor",
        help="bring a board up: adapter, clock, ioctl cost, chips, bound and rate",
        description="Name the I2C adapter and what it accepts in one ioctl, the configured and "
        "measured clock and the cost of one ioctl; find the chips, read each and count "
        "errors over 300 register reads; per scheduler, the computed bound for the "
        "chips found and the rate measured running at it. Takes the bus's lock: "
        "refuses a bus a running daemon holds unless --force. Exit 0: all well; "
        "1: no chip; 2: a warning or a failing chip.",
    )
    p.add_argument("--bus", default="sim", help=f"bus: {ACCEPTED_FORMS} (default: sim)")
    p.add_argument(
        "--scheduler", choices=("naive", "overlapped", "burst"), help="only this scheduler (default: all)"
    )
    p.add_argument(
        "--bus-hz",
        type=float,
        default=400e3,
        help="the clock ftsensord is configured with, Hz (default 400000)",
    )
    p.add_argument(
        "--rate", type=rate_hz, default=100.0, help="the rate `run` would choose for, Hz (default 100)"
    )
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--force", action="store_true", help="go on when another process (a daemon) holds the bus")
    p.add_argument(
        "--real-time",
        action="store_true",
        help="on the simulated bus, spend real time (default: its virtual clock, instant)",
    )
    p.add_argument(
        "--config",
        help="the daemon's configuration: also each sensor's predicted sigma at rest at its "
        "conversion, averaging and estimator, untared",
    )
    p.set_defaults(func=cmd_doctor)


def predicted_sigma(path: str) -> dict[str, Any]:
    """Each sensor's predicted sigma at rest (N, Nm) at the configuration's settings (after its
    sensors' ``accuracy``, if any, chose them), untared: what `status` shows once it runs."""
    from ftsensord.config.file import load_config
    from ftsensord.processing import accuracy
    from ftsensord.processing.filters import WrenchFilter

    config = load_config(path)
    accuracy.apply_accuracy(config)
    # the filter's steady variance factor at the file's rate, averaging and low-pass
    factor = WrenchFilter(config.averaging, config.lowpass_hz, config.rate_hz).factors[-1]
    out: dict[str, Any] = {
        "osr": config.settings.osr,
        "dig_filt": config.settings.dig_filt,
        "averaging": config.averaging,
        "lowpass_hz": config.lowpass_hz,
        "rate_hz": config.rate_hz,
        "sensors": {},
    }
    for s in config.sensors:
        sensor = accuracy.Sensor(s, s.estimator)
        u = accuracy.uncertainty_at(sensor, config.settings)
        out["sensors"][s.name] = {
            "estimator": s.estimator,
            "sigma": u.predicted(factor, None, s.estimator)["sigma"],
        }
    return out


def describe_predicted(p: dict[str, Any]) -> str:
    from ftsensord.processing.uncertainty import sigma_text

    lines = [
        f"predicted sigma at rest, untared (OSR {p['osr']}, DIG_FILT {p['dig_filt']}, averaging "
        f"{p['averaging']}, low-pass {p['lowpass_hz'] or 'off'}, {p['rate_hz']:g} Hz):"
    ]
    for name, s in p["sensors"].items():
        sigma = s["sigma"]
        lines.append(f"  {name} ({s['estimator']}): " + ("unknown" if sigma is None else sigma_text(sigma)))
    return "\n".join(lines)


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


def cmd_doctor(args: argparse.Namespace) -> int:
    from ftsensord.acquire.bound import SCHEDULERS
    from ftsensord.acquire.doctor import doctor, format_doctor

    report = doctor(
        args.bus,
        (args.scheduler,) if args.scheduler else SCHEDULERS,
        bus_hz=args.bus_hz,
        force=args.force,
        real_time=args.real_time,
        rate_hz=args.rate,
    )
    if args.config:
        report["predicted_sigma"] = predicted_sigma(args.config)
    print(json.dumps(report, indent=2) if args.json else format_doctor(report))
    if args.config and not args.json:
        print(describe_predicted(report["predicted_sigma"]))
    if not report["chips"]:
        print(f"no MLX90393 answered on {args.bus} (0x0C-0x1B)", file=sys.stderr)
        return 1
    return 2 if report["warnings"] or any(c["error"] for c in report["chips"]) else 0
