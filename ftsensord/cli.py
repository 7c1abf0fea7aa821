"""The ``ftsensord`` command line.

``main(argv) -> int`` is what the console script runs and what tests call.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence

from . import __version__
from . import mlx90393 as mlx
from .bus import ACCEPTED_FORMS, open_bus
from .errors import FtsensordError
from .scan import ChipReport, scan


def _format_table(reports: list[ChipReport], spec: str) -> str:
    nan3 = [float("nan")] * 3
    lines = [f"{'addr':<5} {'part':<20} {'CONF1':<6} {'CONF2':<6} {'CONF3':<6} "
             f"{'Bx/uT':>9} {'By/uT':>9} {'Bz/uT':>9} {'T/degC':>7}  notes"]
    for r in reports:
        regs = [f"0x{r.registers[i]:04X}" if i in r.registers else "-" for i in range(3)]
        m = r.measurement
        field = nan3 if m is None else [float(v) * 1e6 for v in m.field_t]
        temp = float("nan") if m is None or m.temperature_c is None else m.temperature_c
        notes = []
        if len(r.registers) == 3:
            s = mlx.Settings.from_registers(r.registers)
            notes.append(f"found GAIN_SEL={s.gain_sel} RES={s.res_x}{s.res_y}{s.res_z} "
                         f"OSR={s.osr} DIG_FILT={s.dig_filt}")
        if m is not None and m.any_saturated:
            notes.append("SATURATED " + "".join(a for a, sat in zip("XYZ", m.saturated) if sat))
        if r.error:
            notes.append(f"ERROR: {r.error}")
        lines.append(f"0x{r.address:02X}  {r.part:<20} {regs[0]:<6} {regs[1]:<6} {regs[2]:<6} "
                     f"{field[0]:>9.1f} {field[1]:>9.1f} {field[2]:>9.1f} {temp:>7.2f}  "
                     + "; ".join(notes))
    lines.append(f"{len(reports)} chip(s) found on {spec}")
    return "\n".join(lines)


def cmd_scan(args: argparse.Namespace) -> int:
    bus = open_bus(args.bus)
    try:
        reports = scan(bus)
    finally:
        bus.close()
    if args.json:
        print(json.dumps({"bus": args.bus, "chips": [r.as_dict() for r in reports]}, indent=2))
    else:
        print(_format_table(reports, args.bus))
    if not reports:
        print(f"no MLX90393 answered on {args.bus} (0x0C-0x1B)", file=sys.stderr)
        return 1
    return 2 if any(r.error for r in reports) else 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="ftsensord", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"ftsensord {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("scan", help="find MLX90393 chips on a bus and read each once",
                       description="Probe 0x0C-0x1B and print each chip's part variant, "
                                   "configuration registers (as found) and one reading. "
                                   "Stops and reconfigures the chips: not while the daemon runs. "
                                   "Exit 0: all read; 1: none found; 2: some failed.")
    p.add_argument("--bus", default="sim", help=f"bus to scan: {ACCEPTED_FORMS} (default: sim)")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.set_defaults(func=cmd_scan)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except FtsensordError as exc:
        print(f"ftsensord: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # e.g. /dev/i2c-N missing or not permitted
        print(f"ftsensord: {exc}", file=sys.stderr)
        return 2
